"""One twin of a cell in its own process: attach the shared world, build the twin, serve it.

``CellTwin`` is the factory ``TwinProcess`` runs in each child of a cell (``sim_devices.cell``):
it attaches to the cell's shared world (``World.attach``), builds the one twin it is asked for
(``cameras``, ``robot``, ``rotary_table`` or ``interferometer``) with the twin's own public
constructor, and answers that twin's control API plus the few commands the cell's wiring needs
(``cell.*``: fault plans by transport, the table's re-sync after a re-mount). The twin classes
themselves stay usable on their own, in one process, with a plain ``World``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping
from typing import Any

from sim_devices.control import dispatch
from sim_devices.faults import FaultPlan, fault_kind
from sim_devices.world import World, WorldConfig

KINDS = ("cameras", "robot", "rotary_table", "interferometer")
# Twins with a clock of their own (the 500 Hz controller cycle, the 1 kHz head) run their threads
# under SCHED_RR at this priority when the system allows it, as dedicated hardware keeps its time
# whatever the host does. They use a small part of a core; the kernel's real-time throttling
# (95 % per period by default) still bounds a runaway. The renderer and the table stay normal.
REALTIME_PRIORITY = {"robot": 10, "interferometer": 10}


def scaled_clock(scale: float) -> Callable[[], float]:
    """A monotonic clock that runs ``scale`` times faster than wall time."""
    origin = time.monotonic()
    return lambda: origin + (time.monotonic() - origin) * scale


class CellTwin:
    """Host object (``start``/``stop``/``control``) of one twin process of a cell.

    Parameters
    ----------
    kind : "cameras", "robot", "rotary_table" or "interferometer"
    world_dir : str
        The cell's shared world (``World.share``).
    world : mapping
        ``WorldConfig`` fields (seed included): the constants every process derives alike.
    truth_path : str
        The cell's ground-truth log (every process appends to it).
    settings : mapping
        The twin's own section; for ``robot`` also ``host`` (and ``trajectory_dir``); for ``cameras``
        ``frames`` (the directory), ``optics``, ``stream`` (the cameras' timing) and ``trajectories``
        (the robot's dense truth); for ``rotary_table`` also ``time_scale``.
    """

    def __init__(self, kind: str, world_dir: str, world: Mapping[str, Any], truth_path: str,
                 settings: Mapping[str, Any]) -> None:
        if kind not in KINDS:
            raise ValueError(f"cell twin: unknown kind {kind!r}; expected one of {', '.join(KINDS)}")
        self.kind = kind
        self.world = World.attach(world_dir, WorldConfig.from_dict(world), truth_path)
        self.settings = dict(settings)
        self.twin: Any = None
        self.realtime = False

    def start(self) -> dict[str, Any]:
        self.realtime = self._request_realtime()  # before the twin starts: its threads inherit the policy
        build = {"cameras": self._cameras, "robot": self._robot, "rotary_table": self._rotary_table,
                 "interferometer": self._interferometer}[self.kind]
        self.twin = build()
        return dict(self.twin.start())

    def stop(self) -> None:
        try:
            if self.twin is not None:
                self.twin.stop()
        finally:
            self.world.close()

    def _request_realtime(self) -> bool:
        priority = REALTIME_PRIORITY.get(self.kind)
        if priority is None or not hasattr(os, "sched_setscheduler"):
            return False
        try:
            os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(priority))
        except OSError:  # no CAP_SYS_NICE (a container, CI): the twin runs at normal priority
            return False
        return True

    # ----------------------------------------------------------------------------- the twins
    def _cameras(self) -> Any:
        from sim_devices.camera import CameraFileTwin, OpticalBench

        bench = OpticalBench(self.world, self.settings.get("optics"))
        return CameraFileTwin(self.world, bench, self.settings["frames"], stream=self.settings.get("stream"),
                              trajectories=self.settings.get("trajectories"),
                              render_delay=float(self.settings.get("render_delay", 0.0)),
                              stamp_frames=bool(self.settings.get("stamp_frames", False)))

    def _robot(self) -> Any:
        from sim_devices.ur import URControllerTwin

        settings = dict(self.settings)
        host = settings.pop("host")
        return URControllerTwin(self.world, host, settings)

    def _rotary_table(self) -> Any:
        from sim_devices.rotary_table import RotaryTableTwin

        settings = dict(self.settings)
        time_scale = float(settings.pop("time_scale", 1.0))
        return RotaryTableTwin(self.world, settings, clock=scaled_clock(time_scale))

    def _interferometer(self) -> Any:
        from sim_devices.interferometer import InterferometerTwin

        return InterferometerTwin(self.world, self.settings)

    # ----------------------------------------------------------------------------- control
    def control(self, command: str, /, **kwargs: Any) -> Any:
        """The cell's wiring (``cell.arm``, ``cell.clear``, ``cell.fired``, ``cell.sync``,
        ``cell.realtime``: whether its threads run under SCHED_RR), else the twin's own control API."""
        wiring: dict[str, Callable[..., Any]] = {"cell.arm": self.arm, "cell.clear": self.clear,
                                                 "cell.fired": self.fired, "cell.sync": self.sync,
                                                 "cell.realtime": lambda: self.realtime}
        if command in wiring:
            return dispatch(wiring, command, kwargs, f"{self.kind} twin")
        return self.twin.control(command, **kwargs)

    def _plan(self, transport: str | None) -> FaultPlan:
        if self.kind == "rotary_table":
            return self.twin.faults(transport or "modbus_tcp")
        if self.kind in ("robot", "interferometer"):
            return self.twin.faults
        raise ValueError("simulated cell: the camera file twin takes no faults (the pylon emulator's own "
                         "ForceFailedBuffer is driven through the camera adapter)")

    def arm(self, kind: str, count: int = 1, transport: str | None = None,
            params: Mapping[str, Any] | None = None) -> list[str]:
        """Arm a fault on this twin (the table: on one transport's plan); returns the kinds armed there."""
        plan = self._plan(transport)
        plan.arm(fault_kind(kind), int(count), **dict(params or {}))
        return [armed.kind.value for armed in plan.armed()]

    def clear(self, transport: str | None = None) -> list[str]:
        """Disarm this twin's faults (the robot also leaves a safety stop); returns what is still armed."""
        if self.kind == "robot":
            self.twin.clear_faults()
            return []
        plan = self._plan(transport)
        plan.clear()
        return [armed.kind.value for armed in plan.armed()]

    def fired(self, transport: str | None = None) -> list[tuple[str, dict[str, Any]]]:
        return [(kind.value, params) for kind, params in self._plan(transport).fired()]

    def sync(self) -> None:
        """The rotary table: bring the world up to date at once (after the OPR was re-mounted)."""
        if self.kind != "rotary_table":
            raise ValueError(f"cell twin: sync is a rotary table command, not one of the {self.kind} twin")
        self.twin.sync()
