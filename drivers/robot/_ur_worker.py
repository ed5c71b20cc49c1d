"""The ur_rtde clients in a process of their own: the worker that ``URRobot`` starts and talks to.

Why a process: ur_rtde's constructors hold the GIL while they wait for the controller (a server
that accepts and never answers freezes every thread of the process, signal handlers included),
its control client reconnects on its own after a drop, and an abandoned client can crash the
process with SIGSEGV. Here none of that can reach the engine: the engine process never calls into
ur_rtde, bounds every call it makes to this worker, and kills the worker when a bound is exceeded.

This file runs as a script, ``python -P _ur_worker.py FD PARENT_PID`` (standard library and
ur_rtde only, so it starts in about 0.1 s); ``FD`` is one end of a ``multiprocessing.Pipe``.
Requests are ``(id, method, args)``; replies ``(id, "ok", result)`` or
``(id, "error", kind, operation, cause, broken)``, where ``kind`` is one of ``FAILURE_KINDS`` and
``broken`` says the connection cannot be used again (the engine must ``open()`` anew). The worker
answers quick reads on its main thread and runs every other request on a thread of its own, so
``stop()`` and reads are served while a blocking move is watched.

It never outlives the engine: the main loop exits on the pipe's end of file, a watchdog thread
exits when the parent process changes, and while a client constructor holds the GIL a kernel
timer (SIGALRM, default action) bounds it. On the way out it stops a move in progress.
"""

from __future__ import annotations

import contextlib
import importlib
import math
import os
import queue
import re
import resource
import signal
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from typing import Any, NoReturn

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003
SAFETY_PROTECTIVE_BIT, SAFETY_EMERGENCY_BIT = 1 << 2, 1 << 7
RUNTIME_PLAYING = 2
POSITION_TOLERANCE, ORIENTATION_TOLERANCE = 1e-4, 1e-3  # m, rad: "reached the target" for a blocking move
PAYLOAD_MASS_TOLERANCE, PAYLOAD_COG_TOLERANCE = 1e-6, 1e-7  # kg, m: "the controller took the payload"
# ur_rtde's control script reads a centre of gravity of exactly (0, 0, 0) as "keep the current
# one"; a zero request is sent as 1 nm along z instead, which is physically the same.
ZERO_COG_STAND_IN = 1e-9
PARENT_POLL_PERIOD = 0.25  # s between checks that the engine process still exists
EXIT_BOUND = 3.0  # s a worker that lost its engine may spend stopping a move before the kernel ends it
UNLOCK_RETRY_PERIOD = 0.2  # s between attempts while the controller refuses an early unlock

FAILURE_KINDS = ("timeout", "connection", "protective_stop", "emergency_stop", "program_stopped", "move_failed",
                 "protocol")
QUICK_METHODS = frozenset({"tcp_pose", "joint_positions", "state", "ping", "controller_time"})  # never wait
DONE_MARKER_REGISTER = 12  # output_int_register_12 (+24 upper range): a custom move's end, streamed by RTDE
CUSTOM_MOVE_FUNCTION = "opr_move_circular"
WATCH_PERIOD = 0.0005  # s between polls while a blocking move is watched (the done time's resolution)


class Failure(Exception):
    """A typed failure handed to the engine as ``(kind, operation, cause, broken)``."""

    def __init__(self, kind: str, operation: str, cause: str, *, broken: bool = False) -> None:
        super().__init__(f"{operation}: {cause}")
        self.kind, self.operation, self.cause, self.broken = kind, operation, cause, broken


class _CallThread:
    """Runs client calls on a daemon thread so the caller can stop waiting (the clients release
    the GIL in their methods). A call that overruns leaves its thread behind; the next gets a new one."""

    def __init__(self) -> None:
        self._queue: queue.Queue | None = None
        self._lock = threading.Lock()  # guards _queue; its single thread runs one command at a time

    def _ensure(self) -> queue.Queue:
        if self._queue is None:
            q: queue.Queue = queue.Queue()
            threading.Thread(target=self._loop, args=(q,), name="ur-rtde-call", daemon=True).start()
            self._queue = q
        return self._queue

    @staticmethod
    def _loop(q: queue.Queue) -> None:
        while True:
            fn, box, done = q.get()
            try:
                box["result"] = fn()
            except BaseException as exc:  # handed back to the caller
                box["error"] = exc
            done.set()

    def call(self, fn: Callable[[], Any], timeout: float) -> tuple[bool, Any]:
        """(finished, result); re-raises the call's exception."""
        box: dict[str, Any] = {}
        done = threading.Event()
        with self._lock:
            q = self._ensure()
            q.put((fn, box, done))
        if not done.wait(timeout):
            with self._lock:
                if self._queue is q:
                    self._queue = None  # abandon the stuck thread; the next call gets a fresh one
            return False, None
        if "error" in box:
            raise box["error"]
        return True, box.get("result")


class Session:
    """The two ur_rtde clients of one connection and everything that watches them.

    Every public ``do_<method>`` is one request method; each raises ``Failure`` for what the
    engine must see as a typed device error.
    """

    def __init__(self) -> None:
        self.host = ""
        self.frequency = 500.0
        self.connect_timeout = self.command_timeout = 5.0
        self.move_timeout = 120.0
        self.stale_timeout = 2.0
        self.upper_range_registers = False
        self.greeting = ""
        self.control: Any = None  # ur_rtde ships no type information
        self.receive: Any = None
        self.broken: str | None = None
        self.moving = threading.Event()  # a blocking move is being watched
        self._calls = _CallThread()
        self._motion_lock = threading.Lock()
        self._last_stamp = (-1.0, 0.0)
        self.custom_move = threading.Event()  # a circular move runs as a custom script (stop it by dashboard)

    # ----------------------------------------------------------------------------- connection
    def do_ping(self) -> int:
        return os.getpid()

    def do_open(self, settings: dict[str, Any]) -> None:
        """Probe the controller with plain sockets and timeouts, then construct the ur_rtde clients."""
        self.host = str(settings["host"])
        self.frequency = float(settings["frequency"])
        self.connect_timeout = float(settings["connect_timeout"])
        self.command_timeout = float(settings["command_timeout"])
        self.move_timeout = float(settings["move_timeout"])
        self.stale_timeout = float(settings["stale_timeout"])
        self.upper_range_registers = bool(settings["upper_range_registers"])
        self._probe()
        try:
            rtde_receive = importlib.import_module("rtde_receive")
            rtde_control = importlib.import_module("rtde_control")
        except ImportError as exc:
            raise Failure("connection", "open", f"ur_rtde is not installed ({exc})") from None
        # The constructors hold the GIL while they wait: no thread of this process runs until they
        # return, so only the kernel can bound them if the engine is gone (SIGALRM ends the process).
        signal.setitimer(signal.ITIMER_REAL, 3 * self.connect_timeout + 1.0)
        try:
            self.receive = rtde_receive.RTDEReceiveInterface(self.host, self.frequency, [], False,
                                                             self.upper_range_registers)
            flags = rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
            if self.upper_range_registers:
                flags |= rtde_control.RTDEControlInterface.FLAG_UPPER_RANGE_REGISTERS
            self.control = rtde_control.RTDEControlInterface(self.host, self.frequency, flags)
        except RuntimeError as exc:
            raise Failure("connection", "open", f"ur_rtde could not open {self.host}: {exc}") from None
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
        self._last_stamp = (-1.0, 0.0)

    def _probe(self) -> None:
        """Dashboard greeting, RTDE protocol handshake and script port, each with a timeout."""
        timeout = self.connect_timeout
        try:
            with socket.create_connection((self.host, DASHBOARD_PORT), timeout=timeout) as sock:
                sock.settimeout(timeout)
                greeting = sock.recv(256)
                if not greeting:
                    raise Failure("connection", "open", "the dashboard server closed at once")
                self.greeting = greeting.decode(errors="replace").strip()
            with socket.create_connection((self.host, RTDE_PORT), timeout=timeout) as sock:
                sock.settimeout(timeout)
                sock.sendall(struct.pack(">HBH", 5, 86, 2))  # request protocol version 2
                reply = b""
                while len(reply) < 4:
                    chunk = sock.recv(4 - len(reply))
                    if not chunk:
                        raise Failure("connection", "open", "the RTDE server closed the handshake")
                    reply += chunk
                if reply[2] != 86 or reply[3] != 1:
                    raise Failure("connection", "open", "the RTDE server refused protocol version 2")
            socket.create_connection((self.host, SCRIPT_PORT), timeout=timeout).close()
        except TimeoutError:
            raise Failure("timeout", "open", f"{self.host} accepted but did not answer within {timeout} s") from None
        except OSError as exc:
            raise Failure("connection", "open", f"cannot reach {self.host}: {exc}") from None

    def do_close(self) -> None:
        """Disconnect the clients of a healthy connection (a broken one is left to the process's end)."""
        if self.broken is None:
            for client in (self.control, self.receive):
                if client is not None:
                    with contextlib.suppress(Exception):
                        self._calls.call(client.disconnect, self.command_timeout)

    def stop_motion_on_exit(self) -> None:
        """The engine is gone and nobody watches the robot: stop any move in progress, blocking or
        asynchronous (bounded by the caller's kernel timer)."""
        if self.control is None or self.receive is None or self.broken is not None:
            return
        with contextlib.suppress(Exception):
            if self.custom_move.is_set():
                self._dashboard_stop()
            elif (self.moving.is_set() or self.control.getAsyncOperationProgressEx().isAsyncOperationRunning()
                    or any(abs(v) > 1e-6 for v in self.receive.getActualTCPSpeed())):
                self.control.stopL(2.0, False)

    # ----------------------------------------------------------------------------- helpers
    def _require(self, operation: str) -> tuple[Any, Any]:
        if self.control is None or self.receive is None:
            raise Failure("connection", operation, "not open (call open() first)")
        if self.broken:
            raise Failure("connection", operation, f"connection is broken ({self.broken}); open() again", broken=True)
        if not self.receive.isConnected():
            self.broken = "RTDE data connection lost"
            raise Failure("connection", operation, "the RTDE data connection is lost", broken=True)
        return self.control, self.receive

    def _call(self, operation: str, fn: Callable[[], Any], timeout: float | None = None) -> Any:
        timeout = self.command_timeout if timeout is None else timeout
        try:
            finished, result = self._calls.call(fn, timeout)
        except RuntimeError as exc:
            raise Failure("connection", operation, f"ur_rtde: {exc}") from None
        if not finished:
            self.broken = f"{operation} did not return within {timeout} s"
            raise Failure("timeout", operation, f"no answer within {timeout} s", broken=True)
        return result

    def _check_fresh(self, operation: str) -> None:
        """The RTDE timestamp must advance; a stalled stream counts as a lost connection."""
        stamp = self.receive.getTimestamp()
        now = time.monotonic()
        if stamp != self._last_stamp[0]:
            self._last_stamp = (stamp, now)
        elif now - self._last_stamp[1] > self.stale_timeout:
            raise Failure("connection", operation, f"no new robot data for {now - self._last_stamp[1]:.1f} s")

    def _safety_error(self, operation: str) -> Failure | None:
        bits = int(self.receive.getSafetyStatusBits())
        if bits & SAFETY_EMERGENCY_BIT:
            return Failure("emergency_stop", operation, "the emergency stop is engaged")
        if bits & SAFETY_PROTECTIVE_BIT:
            return Failure("protective_stop", operation, "the robot is in protective stop")
        return None

    def _failure(self, operation: str) -> Failure:
        """Why did the controller refuse or abort ``operation``? The most specific failure."""
        if self.receive is None or not self.receive.isConnected() or not self.control.isConnected():
            return Failure("connection", operation, "the connection to the controller was lost")
        error = self._safety_error(operation)
        if error is not None:
            return error
        if self.receive.getRuntimeState() != RUNTIME_PLAYING:
            return Failure("program_stopped", operation, "the control script is not running on the controller")
        return Failure("move_failed", operation, "the controller rejected the command")

    def _ensure_ready(self, operation: str) -> tuple[Any, Any]:
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
                    raise Failure("program_stopped", operation, "the control script could not be restarted")
                time.sleep(0.005)
        return control, receive

    # ----------------------------------------------------------------------------- readback
    def do_tcp_pose(self) -> list[float]:
        _, receive = self._require("read TCP pose")
        self._check_fresh("read TCP pose")
        return [float(v) for v in receive.getActualTCPPose()]

    def do_joint_positions(self) -> list[float]:
        _, receive = self._require("read joints")
        self._check_fresh("read joints")
        return [float(v) for v in receive.getActualQ()]

    def do_state(self) -> dict[str, Any]:
        receive = self.receive
        if receive is None or not receive.isConnected():
            return {"connected": False}
        bits = int(receive.getSafetyStatusBits())
        return {
            "connected": self.broken is None and self.control is not None and self.control.isConnected(),
            "protective_stop": bool(bits & SAFETY_PROTECTIVE_BIT),
            "emergency_stop": bool(bits & SAFETY_EMERGENCY_BIT),
            "program_running": receive.getRuntimeState() == RUNTIME_PLAYING,
            "steady": all(abs(v) < 1e-6 for v in receive.getActualTCPSpeed()),
            "robot_mode": int(receive.getRobotMode()),
            "safety_mode": int(receive.getSafetyMode()),
        }

    # ----------------------------------------------------------------------------- motion
    def do_forward_kinematics(self, q: list[float]) -> list[float]:
        """The TCP pose of joint positions ``q`` with the current TCP offset (a query, not a motion)."""
        control, _ = self._ensure_ready("moveJ")
        offset = self._call("getTCPOffset", control.getTCPOffset)
        return [float(v) for v in self._call("getForwardKinematics", lambda: control.getForwardKinematics(q, offset))]

    def do_move(self, operation: str, command: list[float], speed: float, acceleration: float, asynchronous: bool,
                timeout: float, target_pose: list[float]) -> float | None:
        """``moveL``/``moveJ`` sent asynchronously on the wire and watched here unless ``asynchronous``;
        returns the controller time at which a blocking move was reported done."""
        with self._motion_lock:
            control, _ = self._ensure_ready(operation)
            send = control.moveL if operation == "moveL" else control.moveJ
            op_before = self._call(operation, lambda: control.getAsyncOperationProgressEx().operationId())
            if not self._call(operation, lambda: send(command, speed, acceleration, True)):
                raise self._failure(operation)
            if asynchronous:
                return None
            return self._watch(operation, op_before, timeout, target_pose)

    def do_move_path(self, path: list[list[float]], asynchronous: bool, timeout: float,
                     target_pose: list[float]) -> float | None:
        """ur_rtde's ``moveL(path)``: rows ``[x, y, z, rx, ry, rz, speed, acceleration, blend]``. The
        client injects the path into its control script, re-uploads it and sends command 45
        (asynchronous on the wire; watched here unless ``asynchronous``)."""
        operation = "moveL path"
        with self._motion_lock:
            control, _ = self._ensure_ready(operation)
            op_before = self._call(operation, lambda: control.getAsyncOperationProgressEx().operationId())
            # Stopping, re-uploading and restarting the script take a few cycles on top of a command.
            if not self._call(operation, lambda: control.moveL(path, True), timeout=2 * self.command_timeout):
                raise self._failure(operation)
            if asynchronous:
                return None
            return self._watch(operation, op_before, timeout, target_pose)

    def _watch(self, operation: str, op_before: int, timeout: float, target_pose: Sequence[float]) -> float:
        self.moving.set()
        try:
            done = self._wait_for_operation(operation, op_before, timeout)
            self._check_reached(operation, target_pose)
        finally:
            self.moving.clear()
        return done

    def _wait_for_operation(self, operation: str, op_before: int, timeout: float) -> float:
        """Poll the async-progress register until the operation that started after ``op_before``
        has finished (its id changed, or it was seen running: a re-uploaded script counts from 0
        again), raising the failure for whatever else happens first. Returns the controller time
        (RTDE ``timestamp``) read right after the finish was seen."""
        control, receive = self.control, self.receive
        deadline = time.monotonic() + timeout
        seen_running = False
        while True:
            if not control.isConnected() or not receive.isConnected():
                self.broken = f"connection lost during {operation}"
                raise Failure("connection", operation, "the connection was lost during the move", broken=True)
            self._check_fresh(operation)
            error = self._safety_error(operation)
            if error is not None:
                raise error
            status = control.getAsyncOperationProgressEx()
            running = status.isAsyncOperationRunning()
            seen_running = seen_running or running
            if (seen_running or status.operationId() != op_before) and not running:
                return float(receive.getTimestamp())
            if receive.getRuntimeState() != RUNTIME_PLAYING:
                # A safety stop also stops the script; its bits may have come with a package newer than the
                # one read above, so ask again before calling it a plain stop of the script.
                raise self._safety_error(operation) or Failure("program_stopped", operation,
                                                               "the control script stopped during the move")
            if time.monotonic() > deadline:
                try:
                    self.do_stop(2.0)
                finally:
                    raise Failure("timeout", operation, f"the move did not finish within {timeout} s")
            time.sleep(WATCH_PERIOD)

    def do_move_circular(self, arcs: list[list[list[float]]], speed: float, acceleration: float, blend: float,
                         timeout: float) -> float:
        """``movec`` arcs (``[via, to]`` pairs, chained with ``blend`` between them) as a custom script
        function (ur_rtde 1.6.5's paths refuse ``MoveC``). The client blocks in
        ``sendCustomScriptFunction`` until the script's done flag, so this thread watches the safety
        bits and the end marker the script writes to an RTDE output register meanwhile. Returns the
        controller time of the first package that carried the marker."""
        operation = "moveC"
        with self._motion_lock:
            control, receive = self._ensure_ready(operation)
            register = DONE_MARKER_REGISTER + (24 if self.upper_range_registers else 0)
            marker = int(receive.getOutputIntRegister(register)) % 1_000_000 + 1  # never the value it holds now
            lines = []
            for index, (via, to) in enumerate(arcs):
                radius = blend if index < len(arcs) - 1 else 0.0
                lines.append(f"movec(p{_script_list(via)}, p{_script_list(to)}, a={acceleration!r}, v={speed!r}, "
                             f"r={radius!r}, mode=0)")
            lines.append(f"write_output_integer_register({register}, {marker})")
            box: dict[str, Any] = {}

            def send() -> None:
                try:
                    box["ok"] = control.sendCustomScriptFunction(CUSTOM_MOVE_FUNCTION, "\n".join(lines))
                except BaseException as exc:  # handed to the watcher
                    box["error"] = exc

            sender = threading.Thread(target=send, name="ur-rtde-custom-move", daemon=True)
            self.custom_move.set()
            self.moving.set()
            try:
                sender.start()
                done = self._watch_custom(operation, sender, box, register, marker, timeout)
            finally:
                self.moving.clear()
                self.custom_move.clear()
            self._check_reached(operation, arcs[-1][1])
            return done

    def _watch_custom(self, operation: str, sender: threading.Thread, box: dict[str, Any], register: int, marker: int,
                      timeout: float) -> float:
        receive = self.receive
        deadline = time.monotonic() + timeout
        done: float | None = None
        while True:
            if done is None:
                value = receive.getOutputIntRegister(register)  # the value first: its package is not newer
                stamp = float(receive.getTimestamp())
                if value == marker:
                    done = stamp
            if not sender.is_alive():
                break
            if not receive.isConnected():
                self.broken = f"connection lost during {operation}"
                raise Failure("connection", operation, "the connection was lost during the move", broken=True)
            try:
                self._check_fresh(operation)
            except Failure as stale:  # the client still waits for its script's flag: this connection is done
                self.broken = f"{stale.cause} during a circular move"
                raise Failure(stale.kind, operation, stale.cause, broken=True) from None
            error = self._safety_error(operation)
            if error is not None:
                # The client waits up to 600 s in sendCustomScript for a flag that will not come.
                self.broken = f"{error.cause} during a circular move (the client waits for its script)"
                raise Failure(error.kind, operation, error.cause, broken=True)
            if time.monotonic() > deadline:
                with contextlib.suppress(Exception):
                    self._dashboard_stop()
                self.broken = f"{operation} did not finish within {timeout} s"
                raise Failure("timeout", operation, f"the move did not finish within {timeout} s", broken=True)
            time.sleep(WATCH_PERIOD)
        if "error" in box or not box.get("ok"):
            cause = f"ur_rtde: {box['error']}" if "error" in box else "the controller did not run the circular move"
            raise Failure("move_failed", operation, cause)
        if done is None:  # the marker came and went before a poll saw it (the script re-upload clears nothing)
            value = receive.getOutputIntRegister(register)
            if value != marker:
                raise Failure("move_failed", operation, "the circular move ended without its end marker")
            done = float(receive.getTimestamp())
        return done

    def _dashboard_stop(self) -> None:
        client = importlib.import_module("dashboard_client").DashboardClient(self.host)
        client.connect(max(1, int(self.connect_timeout * 1000)))
        try:
            client.stop()
        finally:
            with contextlib.suppress(Exception):
                client.disconnect()

    def do_is_steady(self) -> bool:
        """The controller's own ``isSteady()`` (command 47): its encoders at rest."""
        control, _ = self._ensure_ready("isSteady")
        return bool(self._call("isSteady", control.isSteady))

    def do_controller_time(self) -> float:
        """RTDE ``timestamp`` of the latest package: controller seconds."""
        _, receive = self._require("read controller time")
        self._check_fresh("read controller time")
        return float(receive.getTimestamp())

    def _check_reached(self, operation: str, target: Sequence[float]) -> None:
        """The reported pose must reach the target (the data stream may lag the done flag a cycle)."""
        deadline = time.monotonic() + max(0.5, 50.0 / self.frequency)
        while True:
            pose = self.receive.getActualTCPPose()
            dp = math.dist(pose[:3], target[:3])
            dr = rotation_angle_between(pose[3:], target[3:])
            at_rest = max(abs(v) for v in self.receive.getActualTCPSpeed()) < 1e-6
            if dp <= POSITION_TOLERANCE and dr <= ORIENTATION_TOLERANCE and at_rest:
                return  # the data stream shows the final, resting state (it may lag the done flag)
            if time.monotonic() > deadline:
                error = self._safety_error(operation)
                if error is not None:
                    raise error
                if self.receive.getRuntimeState() != RUNTIME_PLAYING:
                    raise Failure("program_stopped", operation, "the control script stopped during the move")
                raise Failure("move_failed", operation,
                              f"stopped {dp * 1e3:.3f} mm / {math.degrees(dr):.4f}° away from the target")
            time.sleep(0.002)

    def do_stop(self, deceleration: float) -> None:
        control, _ = self._require("stopL")
        if self.custom_move.is_set():  # the control script is not running: its stopL would never be answered
            try:
                self._dashboard_stop()
            except RuntimeError as exc:
                raise Failure("connection", "stop", f"dashboard: {exc}") from None
            return
        self._call("stopL", lambda: control.stopL(deceleration, False))

    def do_wait_until_steady(self, timeout: float) -> None:
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
                raise Failure("timeout", "wait until steady", f"the robot was not steady within {timeout} s")
            time.sleep(0.01)

    # ----------------------------------------------------------------------------- TCP and payload
    def do_set_tcp(self, offset: list[float]) -> None:
        control, _ = self._ensure_ready("setTcp")
        if not self._call("setTcp", lambda: control.setTcp(offset)):
            raise self._failure("setTcp")

    def do_tcp_offset(self) -> list[float]:
        control, _ = self._ensure_ready("getTCPOffset")
        try:
            return [float(v) for v in self._call("getTCPOffset", control.getTCPOffset)]
        except Failure as failure:
            if failure.kind != "connection" or failure.broken:
                raise
            raise self._failure("getTCPOffset") from None

    def do_set_payload(self, mass: float, cog: list[float]) -> None:
        """``setPayload`` through the control script, then wait until the controller reports it."""
        control, receive = self._ensure_ready("setPayload")
        sent_cog = cog if any(cog) else [0.0, 0.0, ZERO_COG_STAND_IN]
        if not self._call("setPayload", lambda: control.setPayload(mass, sent_cog)):
            raise self._failure("setPayload")
        deadline = time.monotonic() + max(1.0, 50.0 / self.frequency)
        while True:
            reported_mass, reported_cog = float(receive.getPayload()), list(receive.getPayloadCog())
            if abs(reported_mass - mass) <= PAYLOAD_MASS_TOLERANCE and len(reported_cog) == 3 and all(
                    abs(a - b) <= PAYLOAD_COG_TOLERANCE for a, b in zip(reported_cog, cog)):
                return
            if time.monotonic() > deadline:
                raise Failure("protocol", "setPayload",
                              f"the controller accepted the command but reports {reported_mass:.4f} kg at "
                              f"{_millimetres(reported_cog)} mm, not {mass:.4f} kg at {_millimetres(cog)} mm")
            time.sleep(0.002)

    # ----------------------------------------------------------------------------- dashboard
    def _dashboard(self, operation: str) -> Any:
        """A fresh ur_rtde dashboard connection (the client's own reads time out after 2.5 s)."""
        self._require(operation)
        client = importlib.import_module("dashboard_client").DashboardClient(self.host)
        try:
            client.connect(max(1, int(self.connect_timeout * 1000)))
        except RuntimeError as exc:
            raise Failure("connection", operation, f"dashboard: {exc}") from None
        return client

    def do_identity(self) -> dict[str, str]:
        """Manufacturer (dashboard greeting), model, serial number and PolyScope version."""
        operation = "read robot identity"
        client = self._dashboard(operation)
        try:
            model = client.getRobotModel().strip()
            serial = client.getSerialNumber().strip()  # ur_rtde insists on digits (PolyScope >= 5.6)
            version = client.polyscopeVersion().strip()  # the x.y.z.build part of the answer
        except RuntimeError as exc:
            kind = "protocol" if re.search(r"did not return|not supported", str(exc)) else "connection"
            raise Failure(kind, operation, f"dashboard: {exc}") from None
        finally:
            with contextlib.suppress(Exception):
                client.disconnect()
        if not model or "could not understand" in model.lower() or " " in model:
            raise Failure("protocol", operation, f"the dashboard answered {model!r} to 'get robot model'")
        if not re.fullmatch(r"\d+(\.\d+){3}", version):
            raise Failure("protocol", operation, f"the dashboard answered {version!r} to 'PolyscopeVersion'")
        match = re.fullmatch(r"Connected: (.+?) Dashboard Server", self.greeting)
        manufacturer = match.group(1) if match else "Universal Robots"
        return {"manufacturer": manufacturer, "model": model, "serial_number": serial, "controller_version": version}

    def do_unlock_protective_stop(self, timeout: float) -> None:
        """Release a protective stop, retrying while the controller refuses an early unlock (a real
        controller allows it only 5 s after the stop), then wait for the safety bit to clear."""
        operation = "unlock protective stop"
        _, receive = self._require(operation)
        deadline = time.monotonic() + timeout
        while int(receive.getSafetyStatusBits()) & SAFETY_PROTECTIVE_BIT:
            client = self._dashboard(operation)
            try:
                client.unlockProtectiveStop()
                break
            except RuntimeError as exc:
                answer = str(exc).removeprefix("Unlock protective stop failure: ")
                if "until 5s after" not in answer or time.monotonic() > deadline:
                    raise Failure("protective_stop", operation, f"the controller answered {answer!r}") from None
            finally:
                with contextlib.suppress(Exception):
                    client.disconnect()
            time.sleep(UNLOCK_RETRY_PERIOD)
        while int(receive.getSafetyStatusBits()) & SAFETY_PROTECTIVE_BIT:
            if time.monotonic() > deadline:
                raise Failure("timeout", operation, f"the stop did not clear within {timeout} s")
            time.sleep(0.005)


def _script_list(values: Sequence[float]) -> str:
    """``[v0, v1, ...]`` with every digit of each float (URScript reads Python's repr of a float)."""
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def rotation_angle_between(rotvec_a: Sequence[float], rotvec_b: Sequence[float]) -> float:
    """Angle of R_a^T R_b for two rotation vectors (handles the ±π ambiguity of UR poses)."""
    qa, qb = _quaternion(rotvec_a), _quaternion(rotvec_b)
    dot = abs(sum(a * b for a, b in zip(qa, qb)))
    return 2.0 * math.acos(min(1.0, dot))


def _quaternion(rotvec: Sequence[float]) -> tuple[float, float, float, float]:
    angle = math.sqrt(sum(v * v for v in rotvec))
    if angle < 1e-15:
        return 1.0, 0.0, 0.0, 0.0
    s = math.sin(angle / 2.0) / angle
    return math.cos(angle / 2.0), rotvec[0] * s, rotvec[1] * s, rotvec[2] * s


def _millimetres(vector: Sequence[float]) -> str:
    return "[" + ", ".join(f"{v * 1e3:.3f}" for v in vector) + "]"


# --------------------------------------------------------------------------------------- serving
def serve(conn: Connection, parent_pid: int) -> None:
    """Answer requests until the engine says ``close`` or goes away; never returns."""
    session = Session()
    send_lock = threading.Lock()
    leaving = threading.Lock()

    def leave(code: int) -> NoReturn:
        if not leaving.acquire(blocking=False):
            threading.Event().wait()  # another thread is already on its way out
        signal.setitimer(signal.ITIMER_REAL, EXIT_BOUND)  # the kernel ends us if stopping hangs
        if code != 0:
            session.stop_motion_on_exit()
        os._exit(code)  # no destructors: ur_rtde's can crash on a broken connection

    def reply(message: tuple) -> None:
        with send_lock, contextlib.suppress(OSError):
            conn.send(message)

    def handle(request_id: int, method: str, args: tuple) -> None:
        try:
            result = getattr(session, "do_" + method)(*args)
        except Failure as failure:
            reply((request_id, "error", failure.kind, failure.operation, failure.cause, failure.broken))
        except Exception as exc:  # a client error nobody foresaw: report it, and trust the connection no more
            session.broken = f"{type(exc).__name__}: {exc}"
            reply((request_id, "error", "connection", method, f"ur_rtde: {exc}", True))
        else:
            reply((request_id, "ok", result))

    def watch_parent() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_POLL_PERIOD)
        leave(3)

    threading.Thread(target=watch_parent, name="parent-watch", daemon=True).start()
    reply((0, "ok", os.getpid()))
    while True:
        try:
            request_id, method, args = conn.recv()
        except (EOFError, OSError):
            leave(3)  # the engine is gone
        if method == "close":
            handle(request_id, method, args)
            leave(0)
        elif method in QUICK_METHODS or method == "open":  # open: the constructors hold the GIL anyway
            handle(request_id, method, args)
        else:
            threading.Thread(target=handle, args=(request_id, method, args), name=method, daemon=True).start()


def main(argv: list[str]) -> None:
    fd, parent_pid = int(argv[1]), int(argv[2])
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the engine's to handle (it may stop the robot)
    signal.signal(signal.SIGALRM, signal.SIG_DFL)  # the kernel timer ends the process
    with contextlib.suppress(ValueError, OSError):
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))  # a client crash leaves no core file behind
    if os.getppid() != parent_pid:
        os._exit(3)
    serve(Connection(fd), parent_pid)


if __name__ == "__main__":
    main(sys.argv)
