"""``URRobot``: the ``Robot`` interface on Universal Robots controllers through ``ur_rtde``.

How it keeps every promise of the interface
--------------------------------------------
- **Envelope first.** Every motion is checked against the ``MotionEnvelope`` (target pose, speed,
  acceleration) and refused with ``MotionRefused`` before anything is sent. For joint moves the
  target TCP pose comes from the controller's own forward kinematics (a query, not a motion).
- **Never a hang, never a crash of the engine.** The ur_rtde clients (receive, control and
  dashboard) live in a worker process of their own (``_ur_worker``); this process never calls into
  ur_rtde. Every call to the worker has a deadline derived from the settings; a worker that does
  not answer in time (a constructor holding its GIL on a silent controller, a stuck client) is
  killed and the call raises ``DeviceTimeout``; a worker that dies (SIGSEGV of an abandoned client,
  SIGKILL) makes the pending and every later call raise ``DeviceConnectionError`` at once. Either
  way the connection counts as broken until the next ``open()``, which starts a fresh worker.
  Waiting is interruptible, so the engine's Ctrl-C and SIGTERM handlers always run; the worker
  ignores the terminal's Ctrl-C (the engine decides whether to stop the robot) and exits, stopping
  a move in progress, when the engine process goes away.
- **Moves are asynchronous on the wire.** A blocking ``move_linear`` sends ``moveL(..., async)``
  and the worker watches the controller's async-progress register, safety bits, runtime state and
  data freshness, so a protective stop (``ProtectiveStop``), emergency stop (``EmergencyStop``),
  stopped program (``ProgramStopped``), lost connection (``DeviceConnectionError``), timeout
  (``DeviceTimeout``) or a move that ends away from its target (``MoveFailed``) each raise their
  typed error instead of the client's 300 s wait.
- **Test conditions from the controller.** ``identity()`` asks the dashboard for the model, serial
  number and PolyScope version; ``set_payload()`` sends ``setPayload`` and waits until the
  controller's RTDE ``payload``/``payload_cog`` outputs report the new values.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from drivers._errors import (
    DeviceConnectionError,
    DeviceError,
    DeviceTimeout,
    MotionRefused,
    ProtocolError,
)
from drivers.robot import _ur_worker
from drivers.robot._envelope import MotionEnvelope
from drivers.robot._interface import (
    EmergencyStop,
    MoveFailed,
    ProgramStopped,
    ProtectiveStop,
    RobotIdentity,
    RobotState,
)
from drivers.robot._isolation import WorkerFailure, WorkerLink
from drivers.robot._settings import URRtdeSettings

WORKER_SCRIPT = Path(_ur_worker.__file__)
DASHBOARD_READ_TIMEOUT = 2.5  # s: ur_rtde's dashboard client gives every answer this long
# A worker's failure kinds (``_ur_worker.FAILURE_KINDS``) as the typed errors of ``drivers``.
FAILURE_TYPES: dict[str, type[DeviceError]] = {
    "timeout": DeviceTimeout,
    "connection": DeviceConnectionError,
    "protective_stop": ProtectiveStop,
    "emergency_stop": EmergencyStop,
    "program_stopped": ProgramStopped,
    "move_failed": MoveFailed,
    "protocol": ProtocolError,
}
assert set(FAILURE_TYPES) == set(_ur_worker.FAILURE_KINDS)


class URRobot:
    """A UR e-Series controller through ``rtde_control`` / ``rtde_receive`` (ur_rtde >= 1.6), the
    clients isolated in a worker process.

    Parameters
    ----------
    settings : URRtdeSettings
        Address, RTDE frequency and timeouts (see the model's field descriptions). Each call to the
        worker may take what the worker itself may take for it plus ``command_timeout``; ``open()``
        may take ``6 * connect_timeout + 2`` s after the worker has started (at most 10 s).
    name : str
        Device name used in every error.
    envelope : MotionEnvelope
        The station's motion limits; every target, speed and acceleration is checked against
        them before anything is sent.
    """

    def __init__(self, settings: URRtdeSettings, *, name: str = "robot", envelope: MotionEnvelope) -> None:
        self.name = name
        self.settings = settings
        self.envelope = envelope
        self.host = settings.host
        self.frequency = settings.frequency
        self.connect_timeout = settings.connect_timeout
        self.command_timeout = settings.command_timeout
        self.move_timeout = settings.move_timeout
        self.stale_timeout = settings.stale_timeout
        self.upper_range_registers = settings.upper_range_registers
        self._link: WorkerLink | None = None
        self._opened = False  # the link's open() completed: its worker can answer a polite close
        self._broken: str | None = None
        self._lifecycle = threading.RLock()  # re-entrant: a signal handler may close() while open() waits

    @property
    def worker_pid(self) -> int | None:
        """Process id of the worker holding the ur_rtde clients (None before ``open()``/after ``close()``)."""
        link = self._link
        return None if link is None else link.pid

    # ----------------------------------------------------------------------------- connection
    def open(self) -> None:
        """Start a worker process, which probes the controller with timeouts, then opens the clients.

        A no-op when already open and healthy; after a failure, the old worker is killed first.
        """
        with self._lifecycle:
            if self._link is not None and self._broken is None and self._link.death is None:
                return
            self._discard_link(graceful=False)
            link = WorkerLink(self.name, WORKER_SCRIPT)
            self._link = link
            try:
                link.start()  # its own typed errors: the worker process did not start or died at once
            except BaseException:
                self._discard_link(graceful=False)
                raise
            started = time.monotonic()
            try:
                link.call("open", "open", (self._worker_settings(),), 6 * self.connect_timeout + 2.0)
            except WorkerFailure as failure:
                self._discard_link(graceful=False)
                raise self._typed(failure) from None
            except (DeviceTimeout, DeviceConnectionError) as error:
                self._discard_link(graceful=False)
                # No answer in time, or the kernel timer that bounds the client's constructors fired.
                if isinstance(error, DeviceTimeout) or "SIGALRM" in error.cause:
                    raise DeviceTimeout(self.name, "open", f"{self.host} did not complete the ur_rtde handshake within "
                                        f"{time.monotonic() - started:.1f} s; the client process was stopped") from None
                raise
            except BaseException:  # Ctrl-C or SIGTERM while opening: leave no worker behind
                self._discard_link(graceful=False)
                raise
            self._broken = None
            self._opened = True

    def close(self) -> None:
        """Disconnect the clients and end the worker (killed if it does not exit in time); idempotent."""
        with self._lifecycle:
            self._discard_link(graceful=True)

    def _discard_link(self, *, graceful: bool) -> None:
        link, broken, opened = self._link, self._broken, self._opened
        self._link, self._broken, self._opened = None, None, False
        if link is None:
            return
        if graceful and opened and broken is None and link.death is None:
            link.close(2 * self.command_timeout + 1.0)
        else:
            link.kill()

    def _worker_settings(self) -> dict[str, Any]:
        return {"host": self.host, "frequency": self.frequency, "connect_timeout": self.connect_timeout,
                "command_timeout": self.command_timeout, "move_timeout": self.move_timeout,
                "stale_timeout": self.stale_timeout, "upper_range_registers": self.upper_range_registers}

    def __enter__(self) -> URRobot:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------------------- calls
    def _require(self, operation: str) -> WorkerLink:
        link = self._link
        if link is None:
            raise DeviceConnectionError(self.name, operation, "not open (call open() first)")
        if link.death is not None and self._broken is None:
            self._broken = f"the client process died ({link.death})"
        if self._broken:
            raise DeviceConnectionError(self.name, operation, f"connection is broken ({self._broken}); open() again")
        return link

    def _request(self, operation: str, method: str, *args: Any, bound: float = 0.0) -> Any:
        """``method(*args)`` in the worker, which may itself take ``bound`` seconds for it."""
        link = self._require(operation)
        try:
            return link.call(operation, method, args, bound + self.command_timeout)
        except WorkerFailure as failure:
            if failure.broken:
                self._broken = failure.cause
            raise self._typed(failure) from None
        except DeviceError as error:  # no answer (the worker was killed) or the worker died
            self._broken = error.cause
            raise

    def _typed(self, failure: WorkerFailure) -> DeviceError:
        return FAILURE_TYPES.get(failure.kind, DeviceError)(self.name, failure.operation, failure.cause)

    # ----------------------------------------------------------------------------- readback
    def tcp_pose(self) -> np.ndarray:
        return np.asarray(self._request("read TCP pose", "tcp_pose"), dtype=float)

    def joint_positions(self) -> np.ndarray:
        return np.asarray(self._request("read joints", "joint_positions"), dtype=float)

    def state(self) -> RobotState:
        link = self._link
        if link is None or link.death is not None:
            return RobotState(False, False, False, False, False)
        try:
            data = link.call("read state", "state", (), self.command_timeout)
        except (DeviceError, WorkerFailure):
            return RobotState(False, False, False, False, False)
        if not data["connected"] and "protective_stop" not in data:
            return RobotState(False, False, False, False, False)
        return RobotState(connected=data["connected"] and self._broken is None,
                          protective_stop=data["protective_stop"], emergency_stop=data["emergency_stop"],
                          program_running=data["program_running"], steady=data["steady"],
                          robot_mode=data["robot_mode"], safety_mode=data["safety_mode"])

    def identity(self) -> RobotIdentity:
        """Manufacturer, model, serial number and controller (PolyScope) version, read from the dashboard.

        Raises
        ------
        ProtocolError
            The controller does not answer one of the queries (older PolyScope, another server).
        DeviceConnectionError, DeviceTimeout
            The dashboard could not be reached or did not answer.
        """
        data = self._request("read robot identity", "identity",
                             bound=self.connect_timeout + 4 * DASHBOARD_READ_TIMEOUT)
        return RobotIdentity(**data)

    # ----------------------------------------------------------------------------- motion
    def move_linear(self, pose: np.ndarray, speed: float = 0.25, acceleration: float = 1.2, *,
                    asynchronous: bool = False, timeout: float | None = None) -> None:
        target = np.asarray(pose, dtype=float)
        self.envelope.check_pose(target, self.name)
        self.envelope.check_speed(speed, acceleration, device=self.name)
        self._move("moveL", target, target, speed, acceleration, asynchronous, timeout)

    def move_joint(self, joints: np.ndarray, speed: float = 1.05, acceleration: float = 1.4, *,
                   asynchronous: bool = False, timeout: float | None = None) -> None:
        q = np.asarray(joints, dtype=float)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise MotionRefused(self.name, "check target", f"joints must be 6 finite numbers, got {q!r}")
        self.envelope.check_speed(speed, acceleration, joint=True, device=self.name)
        target = np.asarray(self._request("moveJ", "forward_kinematics", q.tolist(), bound=3 * self.command_timeout))
        if target.shape != (6,):
            raise MoveFailed(self.name, "moveJ", "the controller could not compute the target pose")
        self.envelope.check_pose(target, self.name)
        self._move("moveJ", q, target, speed, acceleration, asynchronous, timeout)

    def _move(self, operation: str, command: np.ndarray, target: np.ndarray, speed: float, acceleration: float,
              asynchronous: bool, timeout: float | None) -> None:
        move_timeout = self.move_timeout if timeout is None else float(timeout)
        # Readiness (script re-upload and its start) and the send are command calls; then the watch.
        bound = 3 * self.command_timeout + (0.0 if asynchronous else move_timeout + 1.0)
        self._request(operation, "move", operation, command.tolist(), float(speed), float(acceleration),
                      bool(asynchronous), move_timeout, target.tolist(), bound=bound)

    def stop(self, deceleration: float = 2.0) -> None:
        self._request("stopL", "stop", float(deceleration), bound=self.command_timeout)

    def wait_until_steady(self, timeout: float = 10.0) -> None:
        self._request("wait until steady", "wait_until_steady", float(timeout), bound=timeout + self.command_timeout)

    # ----------------------------------------------------------------------------- TCP and payload
    def set_tcp(self, offset: np.ndarray) -> None:
        values = np.asarray(offset, dtype=float)
        if values.shape != (6,) or not np.all(np.isfinite(values)):
            raise ValueError(f"{self.name}: TCP offset must be 6 finite numbers, got {values!r}")
        self._request("setTcp", "set_tcp", values.tolist(), bound=3 * self.command_timeout)

    def tcp_offset(self) -> np.ndarray:
        return np.asarray(self._request("getTCPOffset", "tcp_offset", bound=3 * self.command_timeout), dtype=float)

    def set_payload(self, mass_kg: float, cog_m: Sequence[float]) -> None:
        """Set the payload on the controller and wait until it reports it back.

        Parameters
        ----------
        mass_kg : float
            Payload mass, kg (finite, ≥ 0).
        cog_m : sequence of 3 floats
            Its centre of gravity in the tool flange frame, metres.

        Raises
        ------
        ValueError
            For a mass or centre of gravity that is not finite (one line).
        ProtocolError
            The controller accepted the command but does not report the new payload.
        ProtectiveStop, EmergencyStop, ProgramStopped, DeviceConnectionError, DeviceTimeout
            As for any command.
        """
        cog = np.asarray(cog_m, dtype=float)
        if not (np.isfinite(mass_kg) and mass_kg >= 0):
            raise ValueError(f"{self.name}: payload mass must be a finite number >= 0 kg, got {mass_kg!r}")
        if cog.shape != (3,) or not np.all(np.isfinite(cog)):
            raise ValueError(f"{self.name}: payload centre of gravity must be 3 finite numbers (m), got {cog!r}")
        self._request("setPayload", "set_payload", float(mass_kg), cog.tolist(), bound=3 * self.command_timeout + 1.0)

    # ----------------------------------------------------------------------------- recovery
    def unlock_protective_stop(self, timeout: float | None = None) -> None:
        """Release a protective stop through the dashboard (the script is re-uploaded on the next move).

        A real controller refuses an unlock until 5 s after the stop; the worker retries until
        ``timeout`` (default ``command_timeout``) and then waits for the stop to clear. Nothing is
        sent when the robot is not in protective stop.
        """
        wait = self.command_timeout if timeout is None else float(timeout)
        self._request("unlock protective stop", "unlock_protective_stop", wait,
                      bound=wait + self.connect_timeout + DASHBOARD_READ_TIMEOUT)
