"""``ABBRobot``: the ``Robot`` interface on ABB IRC5 controllers through ``abb_robot_client`` (RWS 1.0,
EGM) and ``abb_motion_program_exec``.

How it keeps every promise of the interface
--------------------------------------------
- **Envelope first.** Every target, speed and acceleration is checked against the station's
  ``MotionEnvelope`` before anything is sent (``MotionRefused``). ``move_joint`` cannot be checked
  (RWS 1.0 has no forward kinematics): it is refused unless ``unchecked_joint_moves`` is set.
- **Never a hang.** The clients live in a worker process (``_abb_worker``) behind the same
  deadline-bound pipe as the UR adapter's (``_isolation.WorkerLink``): no answer in time → the
  worker is killed, ``DeviceTimeout``; a dead worker → ``DeviceConnectionError``; either way the
  connection counts as broken until the next ``open()``. Inside the worker every HTTP request
  carries ``command_timeout`` and every wait a deadline.
- **Moves are motion programs.** A move is a short program (MoveL/MoveAbsJ with a fine point,
  MoveL with zones for a blended path, MoveC for arcs) uploaded to the RAMDISK and run by
  RAPID; the worker watches the EGM stream (RAPID execution and motor state at 250 Hz, controller
  time) and RWS, then reads the event log and the joint log the program leaves. A guard stop
  (``ProtectiveStop``), emergency stop (``EmergencyStop``), motors off (``MotorsOff``, a protective
  stop for the engine: it pauses), a RAPID execution error from the event log
  (``RapidExecutionError``), a lost or silent EGM stream or RWS (``DeviceConnectionError``,
  ``DeviceTimeout``) or a move that ends away from its target (``MoveFailed``) each raise their
  typed error.
- **The attained-pose signal.** ``last_move_done_time()`` is the controller time (EGM header
  ``tm``) of the first EGM packet that showed RAPID stopped after the program ran: the fine
  point was reached (RAPID's ``WaitRob \\ZeroSpeed``) and the program ended. ``controller_time()``
  is the latest packet's ``tm``; ``is_steady()`` is the EGM joint feedback unchanged for 50 ms.
- **Acceleration is the controller's.** A motion program carries speed and zone data only (RAPID's
  ``AccSet`` is not in its format): the acceleration is checked against the envelope and not sent.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from drivers._errors import DeviceConnectionError, DeviceError, DeviceTimeout, MotionRefused, ProtocolError
from drivers.robot import _abb_worker
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
from drivers.robot._settings import ABBRwsSettings
from drivers.robot._ur import _per_move, arc_points


class MotorsOff(ProtectiveStop):
    """The controller's motors are off (after a guard stop, an enabling device released, a request):
    motion is impossible until they are switched on (``ABBRobot.motors_on()`` in AUTO mode)."""


class RapidExecutionError(ProgramStopped):
    """RAPID stopped with an execution error; the cause is the event log's text (code, title)."""


WORKER_SCRIPT = Path(_abb_worker.__file__)
FAILURE_TYPES: dict[str, type[DeviceError]] = {
    "timeout": DeviceTimeout,
    "connection": DeviceConnectionError,
    "protective_stop": ProtectiveStop,
    "emergency_stop": EmergencyStop,
    "program_stopped": ProgramStopped,
    "move_failed": MoveFailed,
    "protocol": ProtocolError,
    "motors_off": MotorsOff,
    "rapid_error": RapidExecutionError,
}
assert set(FAILURE_TYPES) == set(_abb_worker.FAILURE_KINDS)


class ABBRobot:
    """An ABB IRC5 controller through RWS, EGM and motion programs, the clients in a worker process.

    Parameters
    ----------
    settings : ABBRwsSettings
        Address, credentials, names on the controller, EGM socket and timeouts (see the model's
        field descriptions). Each call to the worker may take what the worker itself may take for
        it plus ``command_timeout``; ``open()`` may take ``connect_timeout + 3 * command_timeout + 2`` s
        once the worker has started.
    name : str
        Device name used in every error.
    envelope : MotionEnvelope
        The station's motion limits, checked before anything is sent.
    """

    def __init__(self, settings: ABBRwsSettings, *, name: str = "robot", envelope: MotionEnvelope) -> None:
        self.name = name
        self.settings = settings
        self.envelope = envelope
        self.base_url = settings.base_url
        self.command_timeout = settings.command_timeout
        self.move_timeout = settings.move_timeout
        self._link: WorkerLink | None = None
        self._opened = False
        self._broken: str | None = None
        self._last_done: float | None = None
        self._lifecycle = threading.RLock()

    @property
    def worker_pid(self) -> int | None:
        """Process id of the worker holding the ABB clients (None when not open)."""
        link = self._link
        return None if link is None else link.pid

    # ----------------------------------------------------------------------------- connection
    def open(self) -> None:
        """Start the worker, which reaches RWS, binds the EGM socket and waits for the first packet."""
        with self._lifecycle:
            if self._link is not None and self._broken is None and self._link.death is None:
                return
            self._discard_link(graceful=False)
            link = WorkerLink(self.name, WORKER_SCRIPT)
            self._link = link
            try:
                link.start()
                link.call("open", "open", (self.settings.model_dump(),),
                          self.settings.connect_timeout + 3 * self.command_timeout + 2.0)
            except WorkerFailure as failure:
                self._discard_link(graceful=False)
                raise self._typed(failure) from None
            except BaseException:  # no answer, a dead worker, Ctrl-C or SIGTERM: leave no worker behind
                self._discard_link(graceful=False)
                raise
            self._broken = None
            self._opened = True

    def close(self) -> None:
        """Log out, close the EGM socket and end the worker (killed if it does not exit in time); idempotent."""
        with self._lifecycle:
            self._discard_link(graceful=True)

    def _discard_link(self, *, graceful: bool) -> None:
        link, broken, opened = self._link, self._broken, self._opened
        self._link, self._broken, self._opened = None, None, False
        if link is None:
            return
        if graceful and opened and broken is None and link.death is None:
            link.close(self.command_timeout + 1.0)
        else:
            link.kill()

    def __enter__(self) -> ABBRobot:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------------------- calls
    def _request(self, operation: str, method: str, *args: Any, bound: float = 0.0) -> Any:
        """``method(*args)`` in the worker, which may itself take ``bound`` seconds for it."""
        link = self._link
        if link is None:
            raise DeviceConnectionError(self.name, operation, "not open (call open() first)")
        if link.death is not None and self._broken is None:
            self._broken = f"the client process died ({link.death})"
        if self._broken:
            raise DeviceConnectionError(self.name, operation, f"connection is broken ({self._broken}); open() again")
        try:
            return link.call(operation, method, args, bound + self.command_timeout)
        except WorkerFailure as failure:
            if failure.broken:
                self._broken = failure.cause
            raise self._typed(failure) from None
        except DeviceError as error:
            self._broken = error.cause
            raise

    def _typed(self, failure: WorkerFailure) -> DeviceError:
        return FAILURE_TYPES.get(failure.kind, DeviceError)(self.name, failure.operation, failure.cause)

    # ----------------------------------------------------------------------------- readback
    def tcp_pose(self) -> np.ndarray:
        """The TCP of the programs' tool in the base frame (RWS ``robtarget``), [x, y, z, rx, ry, rz]."""
        return np.asarray(self._request("read TCP pose", "tcp_pose", bound=3 * self.command_timeout), dtype=float)

    def joint_positions(self) -> np.ndarray:
        """Axis positions (rad) from RWS ``jointtarget``."""
        return np.asarray(self._request("read joints", "joint_positions", bound=3 * self.command_timeout), dtype=float)

    def state(self) -> RobotState:
        """Panel and RAPID state (``robot_mode``/``safety_mode``: the index of the panel state in
        init, motoroff, motoron, guardstop, emergencystop, emergencystopreset, sysfail)."""
        link = self._link
        if link is None or link.death is not None:
            return RobotState(False, False, False, False, False)
        try:
            data = link.call("read state", "state", (), 6 * self.command_timeout)
        except (DeviceError, WorkerFailure):
            return RobotState(False, False, False, False, False)
        if "protective_stop" not in data:
            return RobotState(False, False, False, False, False)
        return RobotState(connected=data["connected"] and self._broken is None,
                          protective_stop=data["protective_stop"], emergency_stop=data["emergency_stop"],
                          program_running=data["program_running"], steady=data["steady"],
                          robot_mode=data["robot_mode"], safety_mode=data["safety_mode"])

    def identity(self) -> RobotIdentity:
        """ABB, the robot type (``IRB 2600-12/1.65``), the controller's serial (``ctrl-id``) and the
        RobotWare version, read over RWS.

        Raises
        ------
        ProtocolError
            A resource lacks the field (another controller, RobotWare 7).
        DeviceConnectionError, DeviceTimeout
        """
        return RobotIdentity(**self._request("read robot identity", "identity", bound=9 * self.command_timeout))

    def egm_statistics(self) -> dict[str, Any]:
        """EGM packets received and sequence numbers missed since ``open()`` (not in ``Robot``)."""
        return dict(self._request("EGM statistics", "egm_stats"))

    # ----------------------------------------------------------------------------- motion
    def move_linear(self, pose: np.ndarray, speed: float = 0.25, acceleration: float = 1.2, *,
                    asynchronous: bool = False, timeout: float | None = None) -> None:
        """MoveL to ``pose`` with a fine point (speed ``v_tcp`` = ``speed``; a pure reorientation runs at
        ``v_ori`` = ``speed`` rad/s). ``acceleration`` is checked, not sent (the controller plans it)."""
        target = np.asarray(pose, dtype=float)
        self.envelope.check_pose(target, self.name)
        self.envelope.check_speed(speed, acceleration, device=self.name)
        self._move("moveL", target, target, speed, asynchronous, timeout)

    def move_joint(self, joints: np.ndarray, speed: float = 1.05, acceleration: float = 1.4, *,
                   asynchronous: bool = False, timeout: float | None = None) -> None:
        """MoveAbsJ to ``joints`` (rad) with a fine point; allowed only with ``unchecked_joint_moves``.

        ``speed`` (rad/s) is sent as ``v_ori`` (degrees/s) and, for the TCP, ``v_tcp`` = speed × 1 m:
        an ABB controller plans a joint move on its TCP and reorientation speeds.
        """
        q = np.asarray(joints, dtype=float)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise MotionRefused(self.name, "check target", f"joints must be 6 finite numbers, got {q!r}")
        self.envelope.check_speed(speed, acceleration, joint=True, device=self.name)
        if not self.settings.unchecked_joint_moves:
            raise MotionRefused(self.name, "check target", "the TCP pose of a joint target cannot be checked against "
                                "the envelope (RWS 1.0 has no forward kinematics); set unchecked_joint_moves: true "
                                "to allow joint moves")
        self._move("moveJ", q, None, speed, asynchronous, timeout)

    def _move(self, operation: str, command: np.ndarray, target: np.ndarray | None, speed: float,
              asynchronous: bool, timeout: float | None) -> None:
        move_timeout = self.move_timeout if timeout is None else float(timeout)
        bound = 8 * self.command_timeout + (0.0 if asynchronous else move_timeout + 1.0)
        done = self._request(operation, "move", operation, command.tolist(), float(speed), bool(asynchronous),
                             move_timeout, None if target is None else target.tolist(), bound=bound)
        if done is not None:
            self._last_done = float(done)

    def move_path(self, poses: np.ndarray, speed: float | Sequence[float] = 0.25,
                  acceleration: float | Sequence[float] = 1.2, blend_radius: float | Sequence[float] = 0.0, *,
                  asynchronous: bool = False, timeout: float | None = None) -> None:
        """MoveL through the TCP poses ``poses`` (n, 6); a waypoint with ``blend_radius`` r > 0 is a zone
        of TCP radius r (not stopped at), the last one a fine point.

        Raises
        ------
        MotionRefused
            A waypoint outside the envelope, a speed or acceleration over its cap, a blend radius that
            is negative or overlaps a neighbouring one (the controller would shrink it silently).
        ProtectiveStop, MotorsOff, EmergencyStop, RapidExecutionError, MoveFailed, DeviceConnectionError,
        DeviceTimeout
        """
        targets = np.asarray(poses, dtype=float)
        if targets.ndim != 2 or targets.shape[1] != 6 or len(targets) < 1 or not np.all(np.isfinite(targets)):
            raise MotionRefused(self.name, "check path", f"poses must be an (n, 6) array of finite numbers, "
                                f"got shape {targets.shape}")
        n = len(targets)
        speeds, accels, blends = (_per_move(value, n, label, self.name) for value, label in
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
        bound = 8 * self.command_timeout + (0.0 if asynchronous else move_timeout + 1.0)
        done = self._request("moveL path", "move_path", rows, bool(asynchronous), move_timeout,
                             targets[-1].tolist(), bound=bound)
        if done is not None:
            self._last_done = float(done)

    def move_circular(self, via: np.ndarray, to: np.ndarray, speed: float = 0.25, acceleration: float = 1.2, *,
                      blend_radius: float = 0.0, timeout: float | None = None) -> None:
        """MoveC from the current pose through ``via`` to ``to``; (n, 6) arrays chain n arcs with a zone of
        ``blend_radius`` between them and a fine point at the end. Blocking.

        Raises
        ------
        MotionRefused
            A via or target pose, or a point of an arc, outside the envelope; three points on one line;
            a speed or acceleration over its cap — nothing is sent.
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
        done = self._request("moveC", "move_circular", arcs, float(speed), float(blend_radius), move_timeout,
                             bound=8 * self.command_timeout + move_timeout + 1.0)
        self._last_done = float(done)

    def last_move_done_time(self) -> float | None:
        """Controller time (s, EGM ``tm``) of the first EGM packet that showed RAPID stopped after the last
        blocking move's program ran — the robot's attained-pose signal — or None before the first one."""
        return self._last_done

    def controller_time(self) -> float:
        """The controller's clock: the EGM header ``tm`` (ms, as seconds) of the latest packet."""
        return float(self._request("read controller time", "controller_time"))

    def is_steady(self) -> bool:
        """EGM joint feedback unchanged for 50 ms of controller time: the encoders at rest."""
        return bool(self._request("is steady", "is_steady", bound=self.settings.stale_timeout + 1.0))

    def stop(self, deceleration: float = 2.0) -> None:
        """RAPID stop (the controller's own ramp; ``deceleration`` is not sent)."""
        self._request("stop", "stop", float(deceleration), bound=self.command_timeout)

    def wait_until_steady(self, timeout: float = 10.0) -> None:
        self._request("wait until steady", "wait_until_steady", float(timeout), bound=timeout + self.command_timeout)

    def motors_on(self, timeout: float | None = None) -> None:
        """Switch the motors on (RWS ``setctrlstate``; AUTO mode, no guard or emergency stop), not in ``Robot``."""
        wait = self.command_timeout if timeout is None else float(timeout)
        self._request("motors on", "motors_on", wait, bound=wait + 2 * self.command_timeout)

    # ----------------------------------------------------------------------------- TCP and payload
    def set_tcp(self, offset: np.ndarray) -> None:
        """The TCP of the programs' tool (``tframe`` of ``settings.tool``, written over RWS and sent
        with every program)."""
        values = np.asarray(offset, dtype=float)
        if values.shape != (6,) or not np.all(np.isfinite(values)):
            raise ValueError(f"{self.name}: TCP offset must be 6 finite numbers, got {values!r}")
        self._request("set TCP", "set_tcp", values.tolist(), bound=2 * self.command_timeout)

    def tcp_offset(self) -> np.ndarray:
        return np.asarray(self._request("read TCP offset", "tcp_offset", bound=3 * self.command_timeout), dtype=float)

    def set_payload(self, mass_kg: float, cog_m: Sequence[float]) -> None:
        """The tool's load data (``tload``: mass, centre of gravity in the flange frame), written over
        RWS, read back, and sent with every program (RAPID refuses a mass of 0: 1 g stands for none).

        Raises
        ------
        ValueError
            For a mass or centre of gravity that is not finite (one line).
        ProtocolError
            The controller does not hold the values written.
        """
        cog = np.asarray(cog_m, dtype=float)
        if not (np.isfinite(mass_kg) and mass_kg >= 0):
            raise ValueError(f"{self.name}: payload mass must be a finite number >= 0 kg, got {mass_kg!r}")
        if cog.shape != (3,) or not np.all(np.isfinite(cog)):
            raise ValueError(f"{self.name}: payload centre of gravity must be 3 finite numbers (m), got {cog!r}")
        self._request("set payload", "set_payload", float(mass_kg), cog.tolist(), bound=3 * self.command_timeout)
