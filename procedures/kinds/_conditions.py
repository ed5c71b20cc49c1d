"""Test conditions recorded, not typed in: who ran the test, when, on which robot, with what.

At the start of every session (a run or a resume) an ISO run reads the robot's identity from its
controller, sets the payload the procedure states on it, runs or records the warm-up, and notes the
operator: a ``SessionConditions`` record, kept in the session's ``SessionRecord`` and handed to the engine
with the session's first reading (``Reading.session``), which commits it with that sample as a run-level
record. The analysis reads them all (``AnalysisContext.sessions``).
"""

from __future__ import annotations

import getpass
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from drivers import DeviceError
from procedures.kinds._protocol import StepContext
from procedures.store import SessionConditions

OPERATOR_VARIABLE = "INSTRUMENT_OPERATOR"


def operator_of(stated: str | None) -> dict[str, Any]:
    """Who runs the test: the procedure's ``operator``, else ``$INSTRUMENT_OPERATOR``, else the login name."""
    if stated:
        return {"name": stated, "source": "procedure"}
    from_environment = os.environ.get(OPERATOR_VARIABLE, "").strip()
    if from_environment:
        return {"name": from_environment, "source": OPERATOR_VARIABLE}
    try:
        return {"name": getpass.getuser(), "source": "login"}
    except (OSError, KeyError):  # no login name (a container without a passwd entry)
        return {"name": None, "source": None}


def local_time(stamp: float | None) -> str | None:
    """ISO 8601 local date-time with its UTC offset, e.g. ``2025-11-29T18:31:02+01:00``."""
    if stamp is None:
        return None
    return datetime.fromtimestamp(stamp).astimezone().isoformat(timespec="seconds")


def robot_identity(ctx: StepContext) -> dict[str, Any]:
    """The controller's answer (manufacturer, model, serial, software), or the error it gave."""
    try:
        identity = ctx.robot.identity()
    except DeviceError as exc:
        ctx.log("identity", f"robot identity not read: {exc}")
        return {"error": str(exc), "source": "controller"}
    return {"manufacturer": identity.manufacturer, "model": identity.model, "serial_number": identity.serial_number,
            "controller_version": identity.controller_version, "source": "controller"}


def set_payload(ctx: StepContext, mass_kg: float | None, cog_m: Sequence[float]) -> dict[str, Any]:
    """Set the stated payload on the controller (a failure ends the step: the conditions would be wrong)."""
    if mass_kg is None:
        return {"mass_kg": None, "cog_m": None, "set_on_robot": False}
    ctx.robot.set_payload(float(mass_kg), [float(v) for v in cog_m])
    ctx.log("payload", f"payload set on the robot: {mass_kg:g} kg, centre of gravity {list(cog_m)} m")
    return {"mass_kg": float(mass_kg), "cog_m": [float(v) for v in cog_m], "set_on_robot": True}


def warm_up(ctx: StepContext, mode: str, duration_s: float, path: Sequence[Sequence[float]],
            clock: Callable[[], float] = time.monotonic) -> dict[str, Any]:
    """Run the warm-up (``mode`` "run": cycle the robot over ``path`` for ``duration_s``, nothing
    measured; an abort ends it between moves) or record the declared one."""
    if mode != "run" or duration_s <= 0 or not path:
        return {"mode": mode, "duration_s": float(duration_s), "ran_s": None, "moves": None}
    ctx.log("warm_up", f"warm-up: cycling the robot over {len(path)} poses for {duration_s:g} s")
    started, moves = clock(), 0
    while clock() - started < duration_s:
        ctx.move_robot(path[moves % len(path)])
        moves += 1
        ctx.wait(1e-3)  # a safe point: an abort cuts the warm-up short
    ran = clock() - started
    ctx.log("warm_up", f"warm-up done: {moves} moves in {ran:.1f} s")
    return {"mode": mode, "duration_s": float(duration_s), "ran_s": ran, "moves": moves}


@dataclass
class SessionRecord:
    """A kind's memory of the test conditions this session started under (``StepContext.session_state``)."""

    conditions: SessionConditions | None = None
    pending: bool = False  # read, but not yet handed to the engine with a reading

    def start(self, conditions: SessionConditions) -> None:
        self.conditions, self.pending = conditions, True

    def take(self) -> SessionConditions | None:
        """The conditions, once: for the session's first reading (None after that)."""
        if not self.pending:
            return None
        self.pending = False
        return self.conditions
