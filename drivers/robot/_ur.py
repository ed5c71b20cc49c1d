"""``URRobot``: the ``Robot`` interface on Universal Robots controllers through ``ur_rtde``.

How it keeps every promise of the interface
--------------------------------------------
- **Envelope first.** Every motion is checked against the ``MotionEnvelope`` (target pose, speed,
  acceleration) and refused with ``MotionRefused`` before anything is sent. For joint moves the
  target TCP pose comes from the controller's own forward kinematics (a query, not a motion).
- **Never a hang.** The client's constructors hold the GIL while they wait, so ``open()`` first
  probes the dashboard greeting and the RTDE version handshake with plain sockets and timeouts
  (``DeviceTimeout`` / ``DeviceConnectionError``); only a controller that answers is handed to the
  client. Every later call that can wait runs on a worker thread (the client releases the GIL) with
  a deadline; a call that overruns raises ``DeviceTimeout`` and the connection is marked broken.
- **Moves are asynchronous on the wire.** A blocking ``move_linear`` sends ``moveL(..., async)``
  and then watches the controller's async-progress register, safety bits, runtime state and data
  freshness itself, so a protective stop (``ProtectiveStop``), emergency stop (``EmergencyStop``),
  stopped program (``ProgramStopped``), lost connection (``DeviceConnectionError``), timeout
  (``DeviceTimeout``) or a move that ends away from its target (``MoveFailed``) each raise their
  typed error instead of the client's 300 s wait.
"""

from __future__ import annotations

import ctypes
import queue
import socket
import struct
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers._errors import DeviceConnectionError, DeviceError, DeviceTimeout, MotionRefused
from drivers.robot._envelope import MotionEnvelope
from drivers.robot._interface import EmergencyStop, MoveFailed, ProgramStopped, ProtectiveStop, RobotState
from drivers.robot._settings import URRtdeSettings

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003
SAFETY_PROTECTIVE_BIT, SAFETY_EMERGENCY_BIT = 1 << 2, 1 << 7
RUNTIME_PLAYING = 2
POSITION_TOLERANCE, ORIENTATION_TOLERANCE = 1e-4, 1e-3  # m, rad: "reached the target" for a blocking move


# Clients whose connection broke: ur_rtde 1.6.5's control client then loops in its own reconnect
# (its receive thread never resets ``should_reconnect`` and restarts itself), and ``disconnect()`` on
# it can crash the process. They are parked here, never destroyed; their thread gives up by itself
# once the controller refuses connections.
_ABANDONED_CLIENTS: list = []


class _Worker:
    """A daemon thread that runs client calls so the caller can stop waiting (the client releases
    the GIL in its methods). A call that overruns leaves its thread behind, and a new one is used."""

    def __init__(self) -> None:
        self._queue: queue.Queue | None = None

    def _ensure(self) -> queue.Queue:
        if self._queue is None:
            q: queue.Queue = queue.Queue()
            threading.Thread(target=self._loop, args=(q,), name="ur-rtde-call", daemon=True).start()
            self._queue = q
        return self._queue

    @staticmethod
    def _loop(q: queue.Queue) -> None:
        while True:
            item = q.get()
            if item is None:
                return
            fn, box, done = item
            try:
                box["result"] = fn()
            except BaseException as exc:  # handed back to the caller
                box["error"] = exc
            done.set()

    def call(self, fn: Callable[[], Any], timeout: float) -> tuple[bool, Any]:
        """(finished, result); re-raises the call's exception."""
        box: dict[str, Any] = {}
        done = threading.Event()
        self._ensure().put((fn, box, done))
        if not done.wait(timeout):
            self._queue = None  # abandon the stuck thread; the next call gets a fresh one
            return False, None
        if "error" in box:
            raise box["error"]
        return True, box.get("result")

    def close(self) -> None:
        if self._queue is not None:
            self._queue.put(None)
            self._queue = None


class URRobot:
    """A UR e-Series controller through ``rtde_control`` / ``rtde_receive`` (ur_rtde >= 1.6).

    Parameters
    ----------
    settings : URRtdeSettings
        Address, RTDE frequency and timeouts (see the model's field descriptions).
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
        # ur_rtde ships no type information: the clients are typed as what they are to mypy.
        self._control: Any = None
        self._receive: Any = None
        self._worker = _Worker()
        self._broken: str | None = None
        self._last_stamp = (-1.0, 0.0)
        self._lock = threading.RLock()

    # ----------------------------------------------------------------------------- connection
    def open(self) -> None:
        """Probe the controller with timeouts, then open the ur_rtde clients."""
        if self._control is not None and self._broken is None:
            return
        self._drop_clients()
        self._probe()
        try:
            import rtde_control
            import rtde_receive
        except ImportError as exc:  # pragma: no cover - dependency missing
            raise DeviceConnectionError(self.name, "open", f"ur_rtde is not installed ({exc})") from None
        try:
            self._receive = rtde_receive.RTDEReceiveInterface(self.host, self.frequency, [], False,
                                                              self.upper_range_registers)
            flags = rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
            if self.upper_range_registers:
                flags |= rtde_control.RTDEControlInterface.FLAG_UPPER_RANGE_REGISTERS
            self._control = rtde_control.RTDEControlInterface(self.host, self.frequency, flags)
        except RuntimeError as exc:
            self._drop_clients()
            raise DeviceConnectionError(self.name, "open", f"ur_rtde could not open {self.host}: {exc}") from None
        self._broken = None
        self._last_stamp = (-1.0, 0.0)

    def _probe(self) -> None:
        """Dashboard greeting, RTDE protocol handshake and script port, each with a timeout."""
        timeout = self.connect_timeout
        try:
            with socket.create_connection((self.host, DASHBOARD_PORT), timeout=timeout) as sock:
                sock.settimeout(timeout)
                greeting = sock.recv(256)
                if not greeting:
                    raise DeviceConnectionError(self.name, "open", "the dashboard server closed at once")
            with socket.create_connection((self.host, RTDE_PORT), timeout=timeout) as sock:
                sock.settimeout(timeout)
                sock.sendall(struct.pack(">HBH", 5, 86, 2))  # request protocol version 2
                reply = b""
                while len(reply) < 4:
                    chunk = sock.recv(4 - len(reply))
                    if not chunk:
                        raise DeviceConnectionError(self.name, "open", "the RTDE server closed the handshake")
                    reply += chunk
                if reply[2] != 86 or reply[3] != 1:
                    raise DeviceConnectionError(self.name, "open", "the RTDE server refused protocol version 2")
            socket.create_connection((self.host, SCRIPT_PORT), timeout=timeout).close()
        except TimeoutError:
            raise DeviceTimeout(
                self.name, "open", f"{self.host} accepted but did not answer within {timeout} s"
            ) from None
        except OSError as exc:
            raise DeviceConnectionError(self.name, "open", f"cannot reach {self.host}: {exc}") from None

    def close(self) -> None:
        self._drop_clients()
        self._worker.close()

    def _drop_clients(self) -> None:
        control, receive = self._control, self._receive
        self._control = self._receive = None
        if self._broken and control is not None:
            _ABANDONED_CLIENTS.append(control)  # see _ABANDONED_CLIENTS
            # One extra reference that is never released: not even interpreter shutdown may run its
            # destructor (which calls disconnect() and can abort the process).
            ctypes.pythonapi.Py_IncRef(ctypes.py_object(control))
            control = None
        for client in (control, receive):
            if client is not None:
                try:
                    self._worker.call(client.disconnect, self.command_timeout)
                except Exception:
                    pass

    def __enter__(self) -> URRobot:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------------------- helpers
    def _require(self, operation: str):
        if self._control is None or self._receive is None:
            raise DeviceConnectionError(self.name, operation, "not open (call open() first)")
        if self._broken:
            raise DeviceConnectionError(self.name, operation, f"connection is broken ({self._broken}); open() again")
        if not self._receive.isConnected():
            self._broken = "RTDE data connection lost"
            raise DeviceConnectionError(self.name, operation, "the RTDE data connection is lost")
        return self._control, self._receive

    def _call(self, operation: str, fn: Callable[[], Any], timeout: float | None = None) -> Any:
        timeout = self.command_timeout if timeout is None else timeout
        try:
            finished, result = self._worker.call(fn, timeout)
        except RuntimeError as exc:
            raise DeviceConnectionError(self.name, operation, f"ur_rtde: {exc}") from None
        if not finished:
            self._broken = f"{operation} did not return within {timeout} s"
            raise DeviceTimeout(self.name, operation, f"no answer within {timeout} s")
        return result

    def _check_fresh(self, operation: str) -> None:
        """The RTDE timestamp must advance; a stalled stream counts as a lost connection."""
        stamp = self._receive.getTimestamp()
        now = time.monotonic()
        if stamp != self._last_stamp[0]:
            self._last_stamp = (stamp, now)
        elif now - self._last_stamp[1] > self.stale_timeout:
            raise DeviceConnectionError(self.name, operation,
                                        f"no new robot data for {now - self._last_stamp[1]:.1f} s")

    def _safety_error(self, operation: str) -> DeviceError | None:
        bits = int(self._receive.getSafetyStatusBits())
        if bits & SAFETY_EMERGENCY_BIT:
            return EmergencyStop(self.name, operation, "the emergency stop is engaged")
        if bits & SAFETY_PROTECTIVE_BIT:
            return ProtectiveStop(self.name, operation, "the robot is in protective stop")
        return None

    def _failure(self, operation: str) -> DeviceError:
        """Why did the controller refuse or abort ``operation``? The most specific typed error."""
        if self._receive is None or not self._receive.isConnected() or not self._control.isConnected():
            return DeviceConnectionError(self.name, operation, "the connection to the controller was lost")
        error = self._safety_error(operation)
        if error is not None:
            return error
        if self._receive.getRuntimeState() != RUNTIME_PLAYING:
            return ProgramStopped(self.name, operation, "the control script is not running on the controller")
        return MoveFailed(self.name, operation, "the controller rejected the command")

    def _ensure_ready(self, operation: str):
        control, receive = self._require(operation)
        self._check_fresh(operation)
        error = self._safety_error(operation)
        if error is not None:
            raise error
        if receive.getRuntimeState() != RUNTIME_PLAYING:
            # The script ends after a protective stop or a dashboard stop; upload it again once.
            self._call(operation, control.reuploadScript)
            deadline = time.monotonic() + self.command_timeout
            while receive.getRuntimeState() != RUNTIME_PLAYING:
                if time.monotonic() > deadline:
                    raise ProgramStopped(self.name, operation, "the control script could not be restarted")
                time.sleep(0.005)
        return control, receive

    # ----------------------------------------------------------------------------- readback
    def tcp_pose(self) -> np.ndarray:
        _, receive = self._require("read TCP pose")
        self._check_fresh("read TCP pose")
        return np.asarray(receive.getActualTCPPose(), dtype=float)

    def joint_positions(self) -> np.ndarray:
        _, receive = self._require("read joints")
        self._check_fresh("read joints")
        return np.asarray(receive.getActualQ(), dtype=float)

    def state(self) -> RobotState:
        if self._receive is None or not self._receive.isConnected():
            return RobotState(False, False, False, False, False)
        bits = int(self._receive.getSafetyStatusBits())
        speed = np.asarray(self._receive.getActualTCPSpeed(), dtype=float)
        return RobotState(
            connected=self._broken is None and self._control is not None and self._control.isConnected(),
            protective_stop=bool(bits & SAFETY_PROTECTIVE_BIT),
            emergency_stop=bool(bits & SAFETY_EMERGENCY_BIT),
            program_running=self._receive.getRuntimeState() == RUNTIME_PLAYING,
            steady=bool(np.all(np.abs(speed) < 1e-6)),
            robot_mode=int(self._receive.getRobotMode()),
            safety_mode=int(self._receive.getSafetyMode()),
        )

    # ----------------------------------------------------------------------------- motion
    def move_linear(self, pose: np.ndarray, speed: float = 0.25, acceleration: float = 1.2, *,
                    asynchronous: bool = False, timeout: float | None = None) -> None:
        target = np.asarray(pose, dtype=float)
        self.envelope.check_pose(target, self.name)
        self.envelope.check_speed(speed, acceleration, device=self.name)
        self._move("moveL", lambda c: c.moveL(target.tolist(), float(speed), float(acceleration), True),
                   target, asynchronous, timeout)

    def move_joint(self, joints: np.ndarray, speed: float = 1.05, acceleration: float = 1.4, *,
                   asynchronous: bool = False, timeout: float | None = None) -> None:
        q = np.asarray(joints, dtype=float)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise MotionRefused(self.name, "check target", f"joints must be 6 finite numbers, got {q!r}")
        self.envelope.check_speed(speed, acceleration, joint=True, device=self.name)
        control, _ = self._ensure_ready("moveJ")
        offset = self._call("getTCPOffset", control.getTCPOffset)
        target = np.asarray(
            self._call("getForwardKinematics", lambda: control.getForwardKinematics(q.tolist(), offset))
        )
        if target.shape != (6,):
            raise MoveFailed(self.name, "moveJ", "the controller could not compute the target pose")
        self.envelope.check_pose(target, self.name)
        self._move("moveJ", lambda c: c.moveJ(q.tolist(), float(speed), float(acceleration), True),
                   target, asynchronous, timeout)

    def _move(self, operation: str, send: Callable[[Any], bool], target: np.ndarray, asynchronous: bool,
              timeout: float | None) -> None:
        with self._lock:
            control, _ = self._ensure_ready(operation)
            op_before = self._call(operation, lambda: control.getAsyncOperationProgressEx().operationId())
            if not self._call(operation, lambda: send(control)):
                raise self._failure(operation)
            if asynchronous:
                return
            self._wait_for_operation(operation, op_before, self.move_timeout if timeout is None else timeout)
            self._check_reached(operation, target)

    def _wait_for_operation(self, operation: str, op_before: int, timeout: float) -> None:
        """Poll the async-progress register until the operation that started after ``op_before``
        has finished, raising the typed error for whatever else happens first."""
        control, receive = self._control, self._receive
        deadline = time.monotonic() + timeout
        while True:
            if not control.isConnected() or not receive.isConnected():
                self._broken = f"connection lost during {operation}"
                raise DeviceConnectionError(self.name, operation, "the connection was lost during the move")
            self._check_fresh(operation)
            error = self._safety_error(operation)
            if error is not None:
                raise error
            status = control.getAsyncOperationProgressEx()
            if status.operationId() != op_before and not status.isAsyncOperationRunning():
                return
            if receive.getRuntimeState() != RUNTIME_PLAYING:
                raise ProgramStopped(self.name, operation, "the control script stopped during the move")
            if time.monotonic() > deadline:
                try:
                    self.stop()
                finally:
                    raise DeviceTimeout(self.name, operation, f"the move did not finish within {timeout} s")
            time.sleep(0.002)

    def _check_reached(self, operation: str, target: np.ndarray) -> None:
        """The reported pose must reach the target (the data stream may lag the done flag a cycle)."""
        deadline = time.monotonic() + max(0.5, 50.0 / self.frequency)
        while True:
            pose = np.asarray(self._receive.getActualTCPPose(), dtype=float)
            dp = float(np.linalg.norm(pose[:3] - target[:3]))
            dr = _rotation_angle_between(pose[3:], target[3:])
            at_rest = float(np.max(np.abs(self._receive.getActualTCPSpeed()))) < 1e-6
            if dp <= POSITION_TOLERANCE and dr <= ORIENTATION_TOLERANCE and at_rest:
                return  # the data stream shows the final, resting state (it may lag the done flag)
            if time.monotonic() > deadline:
                error = self._safety_error(operation)
                if error is not None:
                    raise error
                if self._receive.getRuntimeState() != RUNTIME_PLAYING:
                    raise ProgramStopped(self.name, operation, "the control script stopped during the move")
                raise MoveFailed(self.name, operation,
                                 f"stopped {dp * 1e3:.3f} mm / {np.degrees(dr):.4f}° away from the target")
            time.sleep(0.002)

    def stop(self, deceleration: float = 2.0) -> None:
        control, _ = self._require("stopL")
        self._call("stopL", lambda: control.stopL(float(deceleration), False))

    def wait_until_steady(self, timeout: float = 10.0) -> None:
        control, _ = self._require("wait until steady")
        deadline = time.monotonic() + timeout
        while True:
            error = self._safety_error("wait until steady")
            if error is not None:
                raise error
            status = control.getAsyncOperationProgressEx()
            if not status.isAsyncOperationRunning() and self._call("isSteady", control.isSteady):
                return
            if time.monotonic() > deadline:
                raise DeviceTimeout(self.name, "wait until steady", f"the robot was not steady within {timeout} s")
            time.sleep(0.01)

    # ----------------------------------------------------------------------------- TCP
    def set_tcp(self, offset: np.ndarray) -> None:
        values = np.asarray(offset, dtype=float)
        if values.shape != (6,) or not np.all(np.isfinite(values)):
            raise ValueError(f"{self.name}: TCP offset must be 6 finite numbers, got {values!r}")
        control, _ = self._ensure_ready("setTcp")
        if not self._call("setTcp", lambda: control.setTcp(values.tolist())):
            raise self._failure("setTcp")

    def tcp_offset(self) -> np.ndarray:
        control, _ = self._ensure_ready("getTCPOffset")
        try:
            return np.asarray(self._call("getTCPOffset", control.getTCPOffset), dtype=float)
        except DeviceConnectionError:
            raise self._failure("getTCPOffset") from None

    # ----------------------------------------------------------------------------- recovery
    def unlock_protective_stop(self) -> None:
        """Ask the dashboard to release a protective stop (the script is re-uploaded on the next move)."""
        reply = self._dashboard("unlock protective stop")
        if "releasing" not in reply.lower():
            raise ProtectiveStop(self.name, "unlock protective stop", f"the controller answered {reply!r}")
        if self._receive is not None:
            deadline = time.monotonic() + self.command_timeout
            while int(self._receive.getSafetyStatusBits()) & SAFETY_PROTECTIVE_BIT:
                if time.monotonic() > deadline:
                    raise DeviceTimeout(self.name, "unlock protective stop", "the stop did not clear")
                time.sleep(0.005)

    def _dashboard(self, command: str) -> str:
        try:
            with socket.create_connection((self.host, DASHBOARD_PORT), timeout=self.command_timeout) as sock:
                sock.settimeout(self.command_timeout)
                reader = sock.makefile("rb")
                reader.readline()  # greeting
                sock.sendall(command.encode() + b"\n")
                return reader.readline().decode(errors="replace").strip()
        except TimeoutError:
            raise DeviceTimeout(self.name, f"dashboard {command!r}", "no answer") from None
        except OSError as exc:
            raise DeviceConnectionError(self.name, f"dashboard {command!r}", str(exc)) from None


def _rotation_angle_between(rotvec_a, rotvec_b) -> float:
    """Angle of R_a^T R_b for two rotation vectors (handles the ±π ambiguity of UR poses)."""
    def matrix(v):
        v = np.asarray(v, dtype=float)
        angle = float(np.linalg.norm(v))
        if angle < 1e-15:
            return np.eye(3)
        k = v / angle
        kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * kx @ kx

    relative = matrix(rotvec_a).T @ matrix(rotvec_b)
    return float(np.arccos(np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0)))
