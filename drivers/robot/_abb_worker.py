"""The ABB clients in a process of their own: the worker that ``ABBRobot`` starts and talks to.

``abb_robot_client``'s ``RWS`` waits on HTTP without a timeout of its own (``requests`` with
none), ``MotionProgramExecClient`` polls the execution state until RAPID stops however long that
takes, and ``EGM`` blocks in ``select``. Here none of that can reach the engine: the engine bounds
every call it makes to this worker and kills the worker when a bound is exceeded; inside, every
HTTP request carries ``command_timeout`` (a session adapter with a default timeout) and every wait
of our own has a deadline, so most failures come back typed before the engine's bound.

This file runs as a script, ``python -P _abb_worker.py FD PARENT_PID`` (standard library and the
ABB clients only). The request protocol and the exit rules are the UR worker's (``_ur_worker``):
requests ``(id, method, args)``, replies ``(id, "ok", result)`` or ``(id, "error", kind, operation,
cause, broken)``; quick reads are answered on the main thread, everything else on a thread of its
own (so ``stop()`` is served while a move is watched); the worker exits, stopping RAPID if a move
may run, when the pipe ends or its parent changes.

What goes over the wire for each call is in ``docs/robot.md`` (ABB section).
"""

from __future__ import annotations

import collections
import contextlib
import importlib
import ipaddress
import math
import os
import re
import resource
import signal
import socket
import sys
import threading
import time
import urllib.parse
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from typing import Any, NoReturn

FAILURE_KINDS = ("timeout", "connection", "protective_stop", "emergency_stop", "program_stopped", "move_failed",
                 "protocol", "motors_off", "rapid_error")
PARENT_POLL_PERIOD = 0.25  # s between checks that the engine process still exists
EXIT_BOUND = 3.0  # s a worker that lost its engine may spend stopping a move before the kernel ends it
QUICK_METHODS = frozenset({"ping", "controller_time"})  # memory reads; every HTTP call runs on a thread of its own
POSITION_TOLERANCE, ORIENTATION_TOLERANCE = 1e-4, 1e-3  # m, rad: "reached the target" for a blocking move
PAYLOAD_MASS_TOLERANCE, PAYLOAD_COG_TOLERANCE = 1e-6, 1e-7  # kg, m: RAPID keeps nine digits
STEADY_WINDOW = 0.05  # s of controller time with unchanged EGM joint feedback: "steady"
STEADY_JOINT_TOLERANCE = 1e-7  # degrees
WATCH_PERIOD = 0.002  # s between looks at the EGM state while a move is watched
RWS_POLL_PERIOD = 0.25  # s between RWS execution-state checks while a move is watched
NO_EXTERNAL_AXES = [9e9] * 6  # RAPID's "not used" value for external axes
PANEL_FAILURES = {"guardstop": ("protective_stop", "the controller is in guard stop"),
                  "emergencystop": ("emergency_stop", "the emergency stop is engaged"),
                  "emergencystopreset": ("emergency_stop", "the emergency stop is being reset"),
                  "motoroff": ("motors_off", "the motors are off"),
                  "sysfail": ("connection", "the controller is in system failure"),
                  "init": ("connection", "the controller is starting")}


class Failure(Exception):
    """A typed failure handed to the engine as ``(kind, operation, cause, broken)``."""

    def __init__(self, kind: str, operation: str, cause: str, *, broken: bool = False) -> None:
        super().__init__(f"{operation}: {cause}")
        self.kind, self.operation, self.cause, self.broken = kind, operation, cause, broken


def quaternion_from_rotvec(rotvec: Sequence[float]) -> list[float]:
    angle = math.sqrt(sum(v * v for v in rotvec))
    if angle < 1e-15:
        return [1.0, 0.0, 0.0, 0.0]
    s = math.sin(angle / 2.0) / angle
    return [math.cos(angle / 2.0), rotvec[0] * s, rotvec[1] * s, rotvec[2] * s]


def rotvec_from_quaternion(q: Sequence[float]) -> list[float]:
    norm = math.sqrt(sum(v * v for v in q))
    w, x, y, z = (v / norm for v in q)
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    if s < 1e-15:
        return [0.0, 0.0, 0.0]
    angle = 2.0 * math.atan2(s, w)
    axis = [x / s, y / s, z / s]
    if w < 1e-9 and max(axis, key=abs) < 0:  # a half turn: ±axis is the same rotation; the positive one, always
        axis = [-v for v in axis]
    return [v * angle for v in axis]


class EgmFeed:
    """``abb_robot_client.egm.EGM`` on a socket bound to ``(host, port)`` (the client binds every
    interface; this project binds loopback unless told otherwise), read on a thread of its own."""

    def __init__(self, egm_class: Any, host: str, port: int) -> None:
        client = egm_class.__new__(egm_class)  # the client's own receive code, on our socket
        client.socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        client.socket.bind((host, port))
        client.send_sequence_number, client.egm_addr, client.count = 0, None, 0
        self.client = client
        self.lock = threading.Lock()
        self.history: collections.deque[tuple[float, tuple[float, ...], bool, bool, int]] = collections.deque(
            maxlen=1000)
        self.packets = 0
        self.missing = 0
        self.last_seqno: int | None = None
        self.received_at = 0.0  # monotonic time of the latest packet
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, name="abb-egm", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                ok, state = self.client.receive_from_robot(0.1)
            except Exception:  # a datagram the client cannot parse: counted as missing, never fatal
                ok, state = False, None
            if not ok or state is None:
                continue
            header = state.robot_message.header
            tm, seqno = header.tm / 1000.0, int(header.seqno)
            joints = tuple(float(v) for v in state.joint_angles) if state.joint_angles is not None else ()
            with self.lock:
                if self.last_seqno is not None and seqno > self.last_seqno + 1:
                    self.missing += seqno - self.last_seqno - 1
                self.last_seqno = seqno
                self.packets += 1
                self.received_at = time.monotonic()
                self.history.append((tm, joints, bool(state.rapid_running), bool(state.motors_on), self.packets))

    def latest(self) -> tuple[float, tuple[float, ...], bool, bool, int] | None:
        with self.lock:
            return self.history[-1] if self.history else None

    def since(self, packet: int) -> list[tuple[float, tuple[float, ...], bool, bool, int]]:
        with self.lock:
            return [entry for entry in self.history if entry[4] > packet]

    def steady(self) -> bool | None:
        """Encoders at rest for ``STEADY_WINDOW`` of controller time (None: not enough feedback yet)."""
        with self.lock:
            entries = list(self.history)
        if not entries:
            return None
        newest = entries[-1]
        if entries[0][0] > newest[0] - STEADY_WINDOW + 1e-9:
            return None  # the feedback does not reach back far enough yet
        window = [e for e in entries if e[0] >= newest[0] - STEADY_WINDOW - 1e-9]
        return all(max(abs(a - b) for a, b in zip(e[1], newest[1])) < STEADY_JOINT_TOLERANCE for e in window)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        with contextlib.suppress(Exception):
            self.client.socket.close()


class Session:
    """The ABB clients of one connection; each ``do_<method>`` is one request method."""

    def __init__(self) -> None:
        self.settings: dict[str, Any] = {}
        self.rws: Any = None
        self.program_client: Any = None
        self.abb: Any = None  # the abb_motion_program_exec module
        self.egm: EgmFeed | None = None
        self.broken: str | None = None
        self.command_timeout = self.connect_timeout = 5.0
        self.stale_timeout = 2.0
        self.moving = threading.Event()
        self.stop_requested = threading.Event()
        self._motion_lock = threading.Lock()
        self.tool_trans = [0.0, 0.0, 0.0]  # mm, the TCP in tool0
        self.tool_rot = [1.0, 0.0, 0.0, 0.0]
        self.load = (0.001, [0.0, 0.0, 0.001])  # kg, mm: RAPID refuses a zero tool mass

    # ----------------------------------------------------------------------------- connection
    def do_ping(self) -> int:
        return os.getpid()

    def do_open(self, settings: dict[str, Any]) -> None:
        """Build the clients with bounded HTTP, check the controller answers, bind EGM and wait for it."""
        self.settings = dict(settings)
        self.command_timeout = float(settings["command_timeout"])
        self.connect_timeout = float(settings["connect_timeout"])
        self.stale_timeout = float(settings["stale_timeout"])
        try:
            rws_module = importlib.import_module("abb_robot_client.rws")
            egm_module = importlib.import_module("abb_robot_client.egm")
            self.abb = importlib.import_module("abb_motion_program_exec")
            adapters = importlib.import_module("requests.adapters")
        except ImportError as exc:
            raise Failure("connection", "open", f"abb-robot-client / abb-motion-program-exec are not installed "
                          f"({exc})") from None
        timeout = (self.connect_timeout, self.command_timeout)
        base: Any = adapters.HTTPAdapter

        class BoundedAdapter(base):  # requests has no session-wide timeout of its own
            def send(self, request: Any, **kwargs: Any) -> Any:
                if kwargs.get("timeout") is None:
                    kwargs["timeout"] = timeout
                return super().send(request, **kwargs)

        self.rws = rws_module.RWS(settings["base_url"], settings["username"], settings["password"])
        self.rws._session.mount("http://", BoundedAdapter())  # the client exposes no other way to bound it
        self.rws._session.mount("https://", BoundedAdapter())
        state = self._rws("open", lambda: self.rws.get_controller_state())
        if state not in PANEL_FAILURES and state != "motoron":
            raise Failure("protocol", "open", f"the controller answered {state!r} for its state")
        self.program_client = self.abb.MotionProgramExecClient(abb_client=self.rws)
        host, port = self._egm_address()
        try:
            self.egm = EgmFeed(egm_module.EGM, host, port)
        except OSError as exc:
            raise Failure("connection", "open", f"cannot bind the EGM socket {host}:{port}: {exc}") from None
        deadline = time.monotonic() + self.connect_timeout
        while self.egm.latest() is None:
            if time.monotonic() > deadline:
                raise Failure("timeout", "open", f"no EGM packet reached {host}:{port} within {self.connect_timeout} s "
                              "(is the controller's UCdevice pointed at this address?)")
            time.sleep(0.005)
        self._read_tool("open")

    def _egm_address(self) -> tuple[str, int]:
        host = self.settings.get("egm_host")
        if host is None:
            url_host = urllib.parse.urlsplit(self.settings["base_url"]).hostname or "127.0.0.1"
            try:
                host = url_host if ipaddress.ip_address(url_host).is_loopback else "127.0.0.1"
            except ValueError:
                host = "127.0.0.1"
        return str(host), int(self.settings["egm_port"])

    def do_close(self) -> None:
        if self.egm is not None:
            self.egm.close()
        if self.rws is not None and self.broken is None:
            with contextlib.suppress(Exception):
                self.rws.close()

    def stop_motion_on_exit(self) -> None:
        """The engine is gone and nobody watches the robot: stop RAPID if a move may be running."""
        if self.rws is not None and (self.moving.is_set() or self._running()):
            with contextlib.suppress(Exception):
                self.rws.stop()

    def _running(self) -> bool:
        latest = self.egm.latest() if self.egm is not None else None
        return bool(latest and latest[2])

    # ----------------------------------------------------------------------------- helpers
    def _rws(self, operation: str, call: Callable[[], Any], *, retries: int = 0) -> Any:
        """One client call; its HTTP failures as typed ones (503 retried ``retries`` times for reads)."""
        requests = importlib.import_module("requests")
        rws_module = importlib.import_module("abb_robot_client.rws")
        attempt = 0
        while True:
            try:
                return call()
            except requests.exceptions.Timeout:
                raise Failure("timeout", operation, f"RWS did not answer within {self.command_timeout} s") from None
            except requests.exceptions.ConnectionError as exc:
                raise Failure("connection", operation, f"cannot reach RWS: {_short(exc)}") from None
            except rws_module.ABBException as exc:
                raise Failure("protocol", operation, f"the controller refused: {exc} (code {exc.code})") from None
            except Exception as exc:
                busy = "503" in str(exc) or "500 Internal" in str(exc)
                if busy and attempt < retries:
                    attempt += 1
                    time.sleep(0.05 * attempt)
                    continue
                if busy:
                    raise Failure("connection", operation, "RWS answered 503 (too many active connections)") from None
                raise Failure("protocol", operation, f"RWS: {_short(exc)}") from None

    def _require(self, operation: str) -> Any:
        if self.rws is None or self.egm is None:
            raise Failure("connection", operation, "not open (call open() first)")
        if self.broken:
            raise Failure("connection", operation, f"connection is broken ({self.broken}); open() again", broken=True)
        return self.rws

    def _fresh(self, operation: str) -> tuple[float, tuple[float, ...], bool, bool, int]:
        """The latest EGM packet; a silent stream counts as a lost connection."""
        assert self.egm is not None
        latest = self.egm.latest()
        silent = time.monotonic() - self.egm.received_at
        if latest is None or silent > self.stale_timeout:
            raise Failure("connection", operation, f"no EGM packet from the controller for {silent:.1f} s")
        return latest

    def _panel(self, operation: str) -> str:
        return str(self._rws(operation, self.rws.get_controller_state, retries=2))

    def _panel_failure(self, operation: str, state: str) -> Failure | None:
        if state == "motoron":
            return None
        kind, cause = PANEL_FAILURES.get(state, ("connection", f"the controller is in {state}"))
        return Failure(kind, operation, cause)

    def _read_tool(self, operation: str) -> None:
        """The TCP and load of the tool the programs use, as the controller holds them."""
        text = self._rws(operation, lambda: self.rws.get_rapid_variable(self.settings["tool"],
                                                                        self.settings["task"]), retries=2)
        numbers = [float(v) for v in re.findall(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?", text)]
        if len(numbers) < 15:
            raise Failure("protocol", operation, f"{self.settings['tool']} is not a tooldata: {text!r}")
        self.tool_trans, self.tool_rot = numbers[0:3], numbers[3:7]
        self.load = (numbers[7], numbers[8:11])

    def _write_tool(self, operation: str) -> None:
        text = "[TRUE,[[{}],[{}]],[{},[{}],[1,0,0,0],0,0,0]]".format(
            ",".join(_num(v) for v in self.tool_trans), ",".join(_num(v) for v in self.tool_rot),
            _num(self.load[0]), ",".join(_num(v) for v in self.load[1]))
        self._rws(operation, lambda: self.rws.set_rapid_variable(self.settings["tool"], text, self.settings["task"]))

    # ----------------------------------------------------------------------------- readback
    def do_tcp_pose(self) -> list[float]:
        rws = self._require("read TCP pose")
        target = self._rws("read TCP pose", lambda: rws.get_robtarget(
            self.settings["mechanical_unit"], self.settings["tool"], self.settings["wobj"], "Base"), retries=2)
        return [*(float(v) * 1e-3 for v in target.trans), *rotvec_from_quaternion([float(v) for v in target.rot])]

    def do_joint_positions(self) -> list[float]:
        rws = self._require("read joints")
        joints = self._rws("read joints", lambda: rws.get_jointtarget(self.settings["mechanical_unit"]), retries=2)
        return [math.radians(float(v)) for v in joints.robax]

    def do_state(self) -> dict[str, Any]:
        if self.rws is None or self.egm is None:
            return {"connected": False}
        state = self._panel("read state")
        execution = self._rws("read state", self.rws.get_execution_state, retries=2)
        latest = self.egm.latest()
        fresh = latest is not None and time.monotonic() - self.egm.received_at <= self.stale_timeout
        return {"connected": self.broken is None and fresh, "protective_stop": state == "guardstop",
                "emergency_stop": state in ("emergencystop", "emergencystopreset"),
                "program_running": execution.ctrlexecstate == "running", "steady": bool(self.egm.steady()),
                "robot_mode": PANEL_CODES.get(state, -1), "safety_mode": PANEL_CODES.get(state, -1)}

    def do_controller_time(self) -> float:
        self._require("read controller time")
        return float(self._fresh("read controller time")[0])

    def do_is_steady(self) -> bool:
        self._require("is steady")
        self._fresh("is steady")
        assert self.egm is not None
        deadline = time.monotonic() + 2 * STEADY_WINDOW + self.stale_timeout
        while True:
            steady = self.egm.steady()
            if steady is not None:
                return steady
            if time.monotonic() > deadline:
                raise Failure("connection", "is steady", "too little EGM feedback to tell")
            time.sleep(WATCH_PERIOD)

    def do_egm_stats(self) -> dict[str, Any]:
        self._require("EGM statistics")
        assert self.egm is not None
        with self.egm.lock:
            return {"packets": self.egm.packets, "missing": self.egm.missing, "last_seqno": self.egm.last_seqno}

    def do_identity(self) -> dict[str, str]:
        """Robot type (``rw/system/robottype``), controller serial (``ctrl/identity``), RobotWare version
        (``rw/system``): the client has no call of its own for them, so its ``_do_get`` (Digest,
        ``?json=1``, its error handling) reads them."""
        operation = "read robot identity"
        rws = self._require(operation)
        try:
            def first_state(path: str) -> dict[str, Any]:
                return self._rws(operation, lambda: rws._do_get(path), retries=2)["_embedded"]["_state"][0]

            robot, ctrl, system = (first_state(p) for p in ("rw/system/robottype", "ctrl/identity", "rw/system"))
            model, serial = robot["robot-type"].strip(), ctrl["ctrl-id"].strip()
            version = (system.get("rwversionname") or system["rwversion"]).strip()
        except (KeyError, IndexError, TypeError, AttributeError) as exc:
            raise Failure("protocol", operation, f"the controller's identity resources lack {exc}") from None
        if not (model and serial and version):
            raise Failure("protocol", operation, "the controller answered an empty robot type, serial or version")
        return {"manufacturer": "ABB", "model": model, "serial_number": serial, "controller_version": version}

    # ----------------------------------------------------------------------------- motion
    def _tooldata(self) -> Any:
        abb = self.abb
        return abb.tooldata(True, abb.pose(list(self.tool_trans), list(self.tool_rot)),
                            abb.loaddata(self.load[0], list(self.load[1]), [1, 0, 0, 0], 0, 0, 0))

    def _robtarget(self, pose: Sequence[float], conf: Sequence[float]) -> Any:
        abb = self.abb
        return abb.robtarget([v * 1e3 for v in pose[:3]], quaternion_from_rotvec(pose[3:]), abb.confdata(*conf),
                             NO_EXTERNAL_AXES)

    def _speed(self, speed: float, pure_rotation: bool = False) -> Any:
        # v_tcp in mm/s; a pure reorientation is planned on v_ori (degrees/s), as the Protocol's rad/s.
        if pure_rotation:
            return self.abb.speeddata(500.0, math.degrees(speed), 5000.0, 1000.0)
        return self.abb.speeddata(speed * 1e3, 500.0, 5000.0, 1000.0)

    def _zone(self, radius: float) -> Any:
        if radius <= 0:
            return self.abb.fine
        mm = radius * 1e3
        return self.abb.zonedata(False, mm, 1.5 * mm, 1.5 * mm, 0.15 * mm, 1.5 * mm, 0.15 * mm)

    def _current(self, operation: str) -> tuple[list[float], list[float]]:
        target = self._rws(operation, lambda: self.rws.get_robtarget(
            self.settings["mechanical_unit"], self.settings["tool"], self.settings["wobj"], "Base"), retries=2)
        pose = [*(float(v) * 1e-3 for v in target.trans), *rotvec_from_quaternion([float(v) for v in target.rot])]
        return pose, [float(v) for v in target.robconf]

    def do_move(self, operation: str, command: list[float], speed: float, asynchronous: bool, timeout: float,
                target_pose: list[float] | None) -> float | None:
        """``moveL`` (a TCP pose) or ``moveJ`` (joints) as a one-command motion program."""
        with self._motion_lock:
            self._ready(operation)
            program = self.abb.MotionProgram(tool=self._tooldata())
            if operation == "moveJ":
                program.MoveAbsJ(self.abb.jointtarget([math.degrees(v) for v in command], NO_EXTERNAL_AXES),
                                 self.abb.speeddata(speed * 1e3, math.degrees(speed), 5000.0, 1000.0), self.abb.fine)
            else:
                current, conf = self._current(operation)  # where it is and in which configuration
                pure = math.dist(current[:3], command[:3]) < 1e-7
                program.MoveL(self._robtarget(command, conf), self._speed(speed, pure), self.abb.fine)
            return self._execute(operation, program, asynchronous, timeout, target_pose)

    def do_move_path(self, rows: list[list[float]], asynchronous: bool, timeout: float,
                     target_pose: list[float]) -> float | None:
        """``MoveL`` through the waypoints; a blend radius becomes the zone's TCP radius (0: a fine point)."""
        operation = "moveL path"
        with self._motion_lock:
            self._ready(operation)
            _, conf = self._current(operation)
            program = self.abb.MotionProgram(tool=self._tooldata())
            for row in rows:
                program.MoveL(self._robtarget(row[:6], conf), self._speed(row[6]), self._zone(row[8]))
            return self._execute(operation, program, asynchronous, timeout, target_pose)

    def do_move_circular(self, arcs: list[list[list[float]]], speed: float, blend: float, timeout: float) -> float:
        """``MoveC`` arcs (``[via, to]`` pairs), the zone ``blend`` between them, a fine point at the end."""
        operation = "moveC"
        with self._motion_lock:
            self._ready(operation)
            _, conf = self._current(operation)
            program = self.abb.MotionProgram(tool=self._tooldata())
            for index, (via, to) in enumerate(arcs):
                zone = self._zone(blend if index < len(arcs) - 1 else 0.0)
                program.MoveC(self._robtarget(via, conf), self._robtarget(to, conf), self._speed(speed), zone)
            done = self._execute(operation, program, False, timeout, arcs[-1][1])
            assert done is not None
            return done

    def _ready(self, operation: str) -> None:
        """Motors on and RAPID stopped (an asynchronous move still running is stopped first)."""
        rws = self._require(operation)
        self._fresh(operation)
        failure = self._panel_failure(operation, self._panel(operation))
        if failure is not None:
            raise failure
        if self._rws(operation, rws.get_execution_state, retries=2).ctrlexecstate != "stopped":
            self._rws(operation, rws.stop)
            deadline = time.monotonic() + self.command_timeout
            while self._rws(operation, rws.get_execution_state, retries=2).ctrlexecstate != "stopped":
                if time.monotonic() > deadline:
                    raise Failure("move_failed", operation, "RAPID did not stop the previous program")
                time.sleep(0.01)

    def _execute(self, operation: str, program: Any, asynchronous: bool, timeout: float,
                 target_pose: Sequence[float] | None) -> float | None:
        """Upload, start and (unless ``asynchronous``) watch one motion program; returns the controller
        time (EGM ``tm``) of the first packet that showed RAPID stopped after it ran."""
        assert self.egm is not None
        latest = self.egm.latest()
        mark = latest[4] if latest else 0
        self.stop_requested.clear()
        prev = self._rws(operation, lambda: self.program_client.execute_motion_program(program, wait=False))
        if asynchronous:
            return None
        self.moving.set()
        try:
            done = self._watch(operation, mark, timeout)
            latest = self.egm.latest()
            if latest is None or not latest[3]:  # the motors went off: the panel says why
                failure = self._panel_failure(operation, self._panel(operation))
                if failure is not None:
                    raise failure
            if self.stop_requested.is_set():
                raise Failure("move_failed", operation, "the move was stopped (stop()) before its end")
            try:
                self.program_client.read_motion_program_result_log(prev)
            except Failure:
                raise
            except Exception as exc:
                raise self._program_failure(operation, exc) from None
        finally:
            self.moving.clear()
        if target_pose is not None:
            self._check_reached(operation, target_pose)
        return done

    def _program_failure(self, operation: str, exc: Exception) -> Failure:
        text = str(exc)
        if "Motion Program Failed at command" in text or "Motion Program Failed," in text:
            code = re.search(r"error code (\d+)", text)
            return Failure("rapid_error", operation, "RAPID execution error" + (f" {code.group(1)}" if code else "")
                           + f": {text}")
        if isinstance(exc, (ConnectionError, TimeoutError)) or "Timeout" in type(exc).__name__:
            return Failure("timeout", operation, f"reading the program's result: {_short(exc)}")
        return Failure("move_failed", operation, f"the program ended without its log: {text}")

    def _watch(self, operation: str, mark: int, timeout: float) -> float:
        assert self.egm is not None
        deadline = time.monotonic() + timeout
        next_poll = time.monotonic() + RWS_POLL_PERIOD
        seen_running = False
        start_mark = cursor = mark
        while True:
            try:
                self._fresh(operation)
            except Failure:
                with contextlib.suppress(Failure):
                    self._rws(operation, self.rws.stop)  # nobody may watch the arm: stop it
                raise
            for tm, _, running, motors_on, packet in self.egm.since(cursor):  # each packet once, in order
                cursor = packet
                seen_running = seen_running or running
                if seen_running and not running:
                    return tm
                if not motors_on:
                    raise self._panel_failure(operation, self._panel(operation)) or Failure(
                        "motors_off", operation, "the motors went off during the move")
            if time.monotonic() >= next_poll:
                next_poll = time.monotonic() + RWS_POLL_PERIOD
                if self._rws(operation, self.rws.get_execution_state, retries=2).ctrlexecstate != "running":
                    # RAPID ran and stopped between two looks, or the EGM packets that show it are late:
                    # the first stopped packet after one that showed it running (or the newest there is).
                    after = self.egm.since(start_mark)
                    if not after:  # no packet since the start: the stream is silent (``_fresh`` decides)
                        time.sleep(WATCH_PERIOD)
                        continue
                    ran = [i for i, e in enumerate(after) if e[2]]
                    stopped = [e for e in after[ran[0]:] if not e[2]] if ran else []
                    if stopped:
                        return stopped[0][0]
                    if seen_running or not ran:
                        time.sleep(RWS_POLL_PERIOD / 5)  # a late packet comes within the EGM period
                        after = self.egm.since(start_mark)
                        return next((e[0] for e in after if not e[2] and e[4] > (after[ran[-1]][4] if ran
                                                                                    else start_mark)), after[-1][0])
            if time.monotonic() > deadline:
                with contextlib.suppress(Failure):
                    self._rws(operation, self.rws.stop)
                raise Failure("timeout", operation, f"the move did not finish within {timeout} s")
            time.sleep(WATCH_PERIOD)

    def _check_reached(self, operation: str, target: Sequence[float]) -> None:
        pose, _ = self._current(operation)
        dp = math.dist(pose[:3], target[:3])
        dr = rotation_angle_between(pose[3:], target[3:])
        if dp > POSITION_TOLERANCE or dr > ORIENTATION_TOLERANCE:
            raise Failure("move_failed", operation,
                          f"stopped {dp * 1e3:.3f} mm / {math.degrees(dr):.4f}° away from the target")

    def do_stop(self, deceleration: float) -> None:
        """RAPID stop: the arm decelerates on its path (the controller's own stop ramp)."""
        rws = self._require("stop")
        self.stop_requested.set()
        self._rws("stop", rws.stop)

    def do_wait_until_steady(self, timeout: float) -> None:
        self._require("wait until steady")
        assert self.egm is not None
        deadline = time.monotonic() + timeout
        while True:
            latest = self._fresh("wait until steady")
            if not latest[3]:
                raise self._panel_failure("wait until steady", self._panel("wait until steady")) or Failure(
                    "motors_off", "wait until steady", "the motors are off")
            if not latest[2] and self.egm.steady():
                return
            if time.monotonic() > deadline:
                raise Failure("timeout", "wait until steady", f"the robot was not steady within {timeout} s")
            time.sleep(0.01)

    def do_motors_on(self, timeout: float) -> None:
        """Switch the motors on (AUTO mode, no safety stop) and wait until the controller says so."""
        operation = "motors on"
        rws = self._require(operation)
        self._rws(operation, lambda: rws.set_controller_state("motoron"))
        deadline = time.monotonic() + timeout
        while (state := self._panel(operation)) != "motoron":
            if time.monotonic() > deadline:
                raise self._panel_failure(operation, state) or Failure("timeout", operation, "motors did not go on")
            time.sleep(0.02)

    # ----------------------------------------------------------------------------- TCP and payload
    def do_set_tcp(self, offset: list[float]) -> None:
        self._require("set TCP")
        self.tool_trans = [v * 1e3 for v in offset[:3]]
        self.tool_rot = quaternion_from_rotvec(offset[3:])
        self._write_tool("set TCP")

    def do_tcp_offset(self) -> list[float]:
        self._require("read TCP offset")
        self._read_tool("read TCP offset")
        return [*(v * 1e-3 for v in self.tool_trans), *rotvec_from_quaternion(self.tool_rot)]

    def do_set_payload(self, mass: float, cog: list[float]) -> None:
        """The tool's load data (``tload``), then read back until the controller holds it."""
        operation = "set payload"
        self._require(operation)
        # RAPID refuses a tool whose mass is not positive: the lightest load it accepts stands for "none".
        self.load = (max(mass, 0.001), [v * 1e3 for v in cog])
        self._write_tool(operation)
        self._read_tool(operation)
        reported_mass, reported_cog = self.load[0], [v * 1e-3 for v in self.load[1]]
        if abs(reported_mass - max(mass, 0.001)) > PAYLOAD_MASS_TOLERANCE or any(
                abs(a - b) > PAYLOAD_COG_TOLERANCE for a, b in zip(reported_cog, cog)):
            raise Failure("protocol", operation, f"the controller holds {reported_mass:.4f} kg at "
                          f"{[round(v * 1e3, 3) for v in reported_cog]} mm, not {mass:.4f} kg")


PANEL_CODES = {name: index for index, name in enumerate(
    ("init", "motoroff", "motoron", "guardstop", "emergencystop", "emergencystopreset", "sysfail"))}


def _num(value: float) -> str:
    return "0" if value == 0 else format(float(value), ".9g")


def _short(exc: BaseException) -> str:
    text = str(exc)
    return text if len(text) < 200 else text[:200] + "…"


def rotation_angle_between(rotvec_a: Sequence[float], rotvec_b: Sequence[float]) -> float:
    """Angle of R_a^T R_b for two rotation vectors."""
    qa, qb = quaternion_from_rotvec(rotvec_a), quaternion_from_rotvec(rotvec_b)
    return 2.0 * math.acos(min(1.0, abs(sum(a * b for a, b in zip(qa, qb)))))


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
        os._exit(code)

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
            reply((request_id, "error", "connection", method, f"ABB client: {exc}", True))
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
        elif method in QUICK_METHODS:
            handle(request_id, method, args)
        else:
            threading.Thread(target=handle, args=(request_id, method, args), name=method, daemon=True).start()


def main(argv: list[str]) -> None:
    fd, parent_pid = int(argv[1]), int(argv[2])
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the engine's to handle (it may stop the robot)
    signal.signal(signal.SIGALRM, signal.SIG_DFL)  # the kernel timer ends the process
    with contextlib.suppress(ValueError, OSError):
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    if os.getppid() != parent_pid:
        os._exit(3)
    serve(Connection(fd), parent_pid)


if __name__ == "__main__":
    main(sys.argv)
