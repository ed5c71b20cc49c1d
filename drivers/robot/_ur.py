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
- **Moves for measuring in motion.** ``move_path`` is ur_rtde's ``moveL(path)`` (linear moves
  through waypoints, corners rounded by a blend radius: the client injects the path into its
  control script and re-uploads it); ``move_circular`` sends ``movec`` arcs as a custom script
  function (ur_rtde 1.6.5's paths refuse ``MoveC``) whose last statement writes an end marker to
  ``output_int_register_12`` (+24): the controller time of the first package carrying it is the
  move's done time. Every blocking move leaves that time in ``last_move_done_time()`` (for moveL,
  moveJ and paths: the RTDE ``timestamp`` read right after the async-progress register showed the
  move finished); ``controller_time()`` is the latest RTDE ``timestamp``; ``is_steady()`` is the
  controller's ``isSteady()`` (its encoders at rest — not the tool's true residual vibration).
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
        self._last_done: float | None = None
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
        done = self._request(operation, "move", operation, command.tolist(), float(speed), float(acceleration),
                             bool(asynchronous), move_timeout, target.tolist(), bound=bound)
        if done is not None:
            self._last_done = float(done)

    def move_path(self, poses: np.ndarray, speed: float | Sequence[float] = 0.25,
                  acceleration: float | Sequence[float] = 1.2, blend_radius: float | Sequence[float] = 0.0, *,
                  asynchronous: bool = False, timeout: float | None = None) -> None:
        """Linear moves through the TCP poses ``poses`` (n, 6), not stopping at a waypoint whose blend
        radius is > 0 (ur_rtde ``moveL(path)``).

        Parameters
        ----------
        poses : (n, 6) array
            Waypoints [x, y, z, rx, ry, rz] (m, rotation vector), the last one the target.
        speed, acceleration : float or n floats
            Tool speed (m/s) and acceleration (m/s²) of each move.
        blend_radius : float or n floats
            Radius (m) of the corner blend at each waypoint (the last one is always 0: the robot
            stops there). A blend may be at most half of either segment it joins.
        asynchronous : bool
            Return once the controller runs the path (``stop()`` interrupts it).
        timeout : float, optional
            Seconds the blocking move may take (default ``move_timeout``).

        Raises
        ------
        MotionRefused
            A waypoint outside the envelope, a speed or acceleration over its cap, a blend radius
            that is negative or overlaps a neighbouring blend — nothing is sent.
        ProtectiveStop, EmergencyStop, ProgramStopped, MoveFailed, DeviceConnectionError, DeviceTimeout
        """
        targets = np.asarray(poses, dtype=float)
        if targets.ndim != 2 or targets.shape[1] != 6 or len(targets) < 1 or not np.all(np.isfinite(targets)):
            raise MotionRefused(self.name, "check path", f"poses must be an (n, 6) array of finite numbers, "
                                f"got shape {targets.shape}")
        n = len(targets)
        speeds, accels, blends = (_per_move(value, n, name, self.name) for value, name in
                                  ((speed, "speed"), (acceleration, "acceleration"), (blend_radius, "blend_radius")))
        for pose in targets:
            self.envelope.check_pose(pose, self.name)
        for v, a in zip(speeds, accels):
            self.envelope.check_speed(float(v), float(a), device=self.name)
        blends[-1] = 0.0
        if np.any(blends < 0) or np.any(blends > 2.0):
            raise MotionRefused(self.name, "check path", "blend radii must lie in [0, 2] m")
        if n > 1 and np.any(blends[:-1] > 0):
            corners = np.vstack([self.tcp_pose()[None, :3], targets[:, :3]])
            segments = np.linalg.norm(np.diff(corners, axis=0), axis=1)
            for i in range(n - 1):
                limit = 0.5 * min(segments[i], segments[i + 1])
                if blends[i] > limit + 1e-12:
                    raise MotionRefused(self.name, "check path",
                                        f"blend radius {blends[i] * 1e3:.3f} mm at waypoint {i + 1} overlaps its "
                                        f"neighbours (at most {limit * 1e3:.3f} mm: half of either segment)")
        rows = [[*map(float, pose), float(v), float(a), float(r)] for pose, v, a, r in zip(targets, speeds, accels,
                                                                                        blends)]
        move_timeout = self.move_timeout if timeout is None else float(timeout)
        bound = 5 * self.command_timeout + (0.0 if asynchronous else move_timeout + 1.0)
        done = self._request("moveL path", "move_path", rows, bool(asynchronous), move_timeout,
                             targets[-1].tolist(), bound=bound)
        if done is not None:
            self._last_done = float(done)

    def move_circular(self, via: np.ndarray, to: np.ndarray, speed: float = 0.25, acceleration: float = 1.2, *,
                      blend_radius: float = 0.0, timeout: float | None = None) -> None:
        """Circular move(s) (URScript ``movec``, orientation interpolated to the target's): from the
        current TCP pose through ``via`` to ``to``; with (n, 6) arrays, n arcs one after the other,
        blended with ``blend_radius`` where they meet (two half circles make a full one). Blocking.

        Raises
        ------
        MotionRefused
            A via or target pose, or a point of an arc, outside the envelope; three points on one
            line; a speed or acceleration over its cap — nothing is sent.
        ProtectiveStop, EmergencyStop, MoveFailed, DeviceConnectionError, DeviceTimeout
            A fault during the move leaves ur_rtde's client waiting for its custom script, so the
            connection counts as broken afterwards (``open()`` again).
        """
        vias = np.atleast_2d(np.asarray(via, dtype=float))
        tos = np.atleast_2d(np.asarray(to, dtype=float))
        if vias.shape != tos.shape or vias.shape[1] != 6 or not (np.all(np.isfinite(vias)) and
                                                                   np.all(np.isfinite(tos))):
            raise MotionRefused(self.name, "check arc", "via and to must be finite poses of the same shape (6,) or "
                                f"(n, 6); got {vias.shape} and {tos.shape}")
        self.envelope.check_speed(float(speed), float(acceleration), device=self.name)
        if not (np.isfinite(blend_radius) and 0 <= blend_radius <= 2.0):
            raise MotionRefused(self.name, "check arc", "blend_radius must lie in [0, 2] m")
        start = self.tcp_pose()[:3]
        for v, t in zip(vias, tos):
            self.envelope.check_pose(v, self.name)
            self.envelope.check_pose(t, self.name)
            for point in arc_points(start, v[:3], t[:3], self.name):
                self.envelope.check_pose(np.concatenate([point, t[3:]]), self.name)
            start = t[:3]
        move_timeout = self.move_timeout if timeout is None else float(timeout)
        arcs = [[v.tolist(), t.tolist()] for v, t in zip(vias, tos)]
        done = self._request("moveC", "move_circular", arcs, float(speed), float(acceleration), float(blend_radius),
                             move_timeout, bound=5 * self.command_timeout + move_timeout + 1.0)
        self._last_done = float(done)

    def last_move_done_time(self) -> float | None:
        """Controller time (s, RTDE ``timestamp``) at which the last blocking move was reported done —
        the robot's attained-pose signal — or None before the first one."""
        return self._last_done

    def controller_time(self) -> float:
        """The controller's clock: RTDE ``timestamp`` (s since the controller started) of the latest package."""
        return float(self._request("read controller time", "controller_time"))

    def is_steady(self) -> bool:
        """The controller's ``isSteady()``: its encoders (not the tool) at rest."""
        return bool(self._request("isSteady", "is_steady", bound=3 * self.command_timeout))

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


def _per_move(value: float | Sequence[float], n: int, name: str, device: str) -> np.ndarray:
    array = np.broadcast_to(np.asarray(value, dtype=float), (n,)).copy() if np.ndim(value) == 0 else \
        np.asarray(value, dtype=float)
    if array.shape != (n,) or not np.all(np.isfinite(array)):
        raise MotionRefused(device, "check path", f"{name} must be one number or one per waypoint ({n})")
    return array


def arc_points(start: np.ndarray, via: np.ndarray, end: np.ndarray, device: str, samples: int = 32) -> np.ndarray:
    """Points along the circular arc from ``start`` through ``via`` to ``end`` (for the envelope check)."""
    a, b = via - start, end - start
    normal = np.cross(a, b)
    area = float(np.linalg.norm(normal))
    if area < 1e-12 or min(np.linalg.norm(a), np.linalg.norm(b), np.linalg.norm(end - via)) < 1e-6:
        raise MotionRefused(device, "check arc", "start, via and target must be three distinct points not on one line")
    center = start + (np.dot(a, a) * np.cross(b, normal) + np.dot(b, b) * np.cross(normal, a)) / (2.0 * area**2)
    radius = float(np.linalg.norm(start - center))
    e1 = (start - center) / radius
    e2 = np.cross(normal / area, e1)
    sweep = float(np.arctan2((end - center) @ e2, (end - center) @ e1) % (2 * np.pi))
    phi = np.linspace(0.0, sweep, samples)
    return center + radius * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
