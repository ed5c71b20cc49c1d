"""The three TCP servers of the UR twin: RTDE (30004), dashboard (29999) and script (30003).

Each server owns its listening socket and one thread per connection, and can drop every
connection on demand (the ``disconnect`` fault). Nothing here blocks without a timeout, so
``stop()`` always returns.
"""

from __future__ import annotations

import select
import socket
import struct
import threading
import time
from collections.abc import Callable
from typing import Any

from sim_devices.faults import FaultKind
from sim_devices.ur._controller import (
    RUNTIME_PLAYING,
    SAFETY_BIT_ESTOP,
    SAFETY_BIT_PROTECTIVE,
    URController,
)
from sim_devices.ur._fields import INPUT_FIELDS, OUTPUT_FIELDS, Recipe, parse_names
from sim_devices.ur._script import ControlScript, recognise_control_script

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003
V, v, O, I, S, P, U, M = 86, 118, 79, 73, 83, 80, 85, 77  # RTDE package types


class TcpServer:
    """A listening socket whose connections each run ``handler(sock, server)`` in a thread."""

    def __init__(self, host: str, port: int, handler: Callable[[socket.socket, TcpServer], None], name: str) -> None:
        self.host, self.port, self.name = host, port, name
        self.handler = handler
        self.running = threading.Event()
        self._connections: set[socket.socket] = set()
        self._lock = threading.Lock()
        self._listener: socket.socket | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind((self.host, self.port))
        listener.listen(8)
        listener.settimeout(0.2)
        self.port = listener.getsockname()[1]
        self._listener = listener
        self.running.set()
        self._thread = threading.Thread(target=self._accept_loop, args=(listener,), name=f"ur-{self.name}-accept",
                                        daemon=True)
        self._thread.start()

    def _accept_loop(self, listener: socket.socket) -> None:
        while self.running.is_set():
            try:
                sock, _ = listener.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._connections.add(sock)
            threading.Thread(target=self._serve, args=(sock,), name=f"ur-{self.name}-conn", daemon=True).start()

    def _serve(self, sock: socket.socket) -> None:
        try:
            self.handler(sock, self)
        except (OSError, ConnectionError, ValueError, struct.error):
            pass  # a client that goes away, or sends garbage, only loses its own connection
        finally:
            with self._lock:
                self._connections.discard(sock)
            try:
                sock.close()
            except OSError:
                pass

    def drop_connections(self) -> None:
        with self._lock:
            connections = list(self._connections)
        for sock in connections:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def stop(self) -> None:
        self.running.clear()
        if self._listener is not None:
            self._listener.close()
        self.drop_connections()
        if self._thread is not None:
            self._thread.join(2.0)

    @property
    def connection_count(self) -> int:
        with self._lock:
            return len(self._connections)


def _recv_exact(sock: socket.socket, count: int, running: threading.Event) -> bytes:
    data = b""
    while len(data) < count:
        if not running.is_set():
            raise ConnectionError("server stopping")
        ready, _, _ = select.select([sock], [], [], 0.2)
        if not ready:
            continue
        chunk = sock.recv(count - len(data))
        if not chunk:
            raise ConnectionError("peer closed")
        data += chunk
    return data


# --------------------------------------------------------------------------------------- RTDE
# Dashboard commands the twin acknowledges without changing its state, with PolyScope's replies.
DASHBOARD_FIXED_REPLIES = {
    "close safety popup": "closing safety popup",
    "restart safety": "Restarting safety",
    "power on": "Powering on",
    "power off": "Powering off",
    "brake release": "Brake releasing",
    "get loaded program": "No program loaded",
    "isprogramsaved": "false <unnamed>",
    "close popup": "closing popup",
}


class RTDEHandler:
    """One RTDE session: version handshake, recipes, start/pause, streaming, input packages."""

    def __init__(self, controller: URController, registry: InputOwnership) -> None:
        self.c = controller
        self.registry = registry

    def __call__(self, sock: socket.socket, server: TcpServer) -> None:
        c = self.c
        output: Recipe | None = None
        inputs: dict[int, Recipe] = {}
        started = False
        period = 1.0 / 125.0
        next_send = 0.0
        getters: list[Callable[[dict[str, Any]], object]] = []
        owner = object()
        try:
            while server.running.is_set():
                timeout = max(0.0, next_send - time.monotonic()) if started else 0.2
                ready, _, _ = select.select([sock], [], [], min(timeout, 0.2))
                if ready:
                    size, kind = struct.unpack(">HB", _recv_exact(sock, 3, server.running))
                    payload = _recv_exact(sock, size - 3, server.running) if size > 3 else b""
                    if kind != U:
                        self._setup_delay()
                    if kind == V:
                        self._send(sock, V, struct.pack(">B", 1))
                    elif kind == v:
                        self._send(sock, v, struct.pack(">IIII", *c.config.version))
                    elif kind == O:
                        frequency = struct.unpack(">d", payload[:8])[0]
                        output = Recipe(1, parse_names(payload[8:]), OUTPUT_FIELDS)
                        getters = [self._getter(name) for name in output.names] if output.valid else []
                        cap = c.config.max_stream_rate
                        rate = min(frequency, cap) if cap else frequency
                        period = 1.0 / max(rate, 1.0)
                        self._send(sock, O, output.reply_payload())
                    elif kind == I:
                        recipe = Recipe(len(inputs) + 1, parse_names(payload), INPUT_FIELDS)
                        if recipe.valid and not self.registry.claim(owner, recipe.names):
                            recipe.types = ["IN_USE" if self.registry.taken_by_other(owner, n) else t
                                            for n, t in zip(recipe.names, recipe.types)]
                            self._send(sock, I, struct.pack(">B", 0) + ",".join(recipe.types).encode())
                            continue
                        if recipe.valid:
                            inputs[recipe.id] = recipe
                        self._send(sock, I, recipe.reply_payload())
                    elif kind == S:
                        ok = output is not None and output.valid
                        self._send(sock, S, struct.pack(">B", 1 if ok else 0))  # reply BEFORE the first data
                        started = ok
                        next_send = time.monotonic()
                    elif kind == P:
                        started = False
                        self._send(sock, P, struct.pack(">B", 1))
                    elif kind == U and payload:
                        input_recipe = inputs.get(payload[0])
                        if input_recipe is not None:
                            c.set_inputs(input_recipe.unpack(payload[1:]))
                    continue
                now = time.monotonic()
                if started and output is not None and now >= next_send:
                    next_send = max(next_send + period, now + 0.25 * period)
                    if now < c.stream_stall_until:
                        continue
                    stall = c.faults.take(FaultKind.STALL)
                    if stall is not None:
                        c.stream_stall_until = now + float(stall.params.get("seconds", 3.0))
                        c.log(f"RTDE stream stalled for {stall.params.get('seconds', 3.0)} s (injected)")
                        continue
                    snapshot = c.snapshot
                    data = output.pack([get(snapshot) for get in getters])
                    self._send(sock, U, data)
        finally:
            self.registry.release(owner)

    def _setup_delay(self) -> None:
        armed = self.c.faults.peek(FaultKind.SLOW)
        if armed is not None:
            time.sleep(float(armed.params.get("seconds", 0.5)))

    def _getter(self, name: str) -> Callable[[dict[str, Any]], object]:
        c = self.c
        if name == "timestamp":
            # The controller's clock runs on while the stream is served, even when the control
            # thread is busy (e.g. publishing a settled pose to the world, which renders frames).
            return lambda s: c.sim_time()
        if name.startswith("output_int_register_"):
            index = int(name.rsplit("_", 1)[1])
            return lambda s: c.out_int[index]
        if name.startswith("output_double_register_"):
            index = int(name.rsplit("_", 1)[1])
            return lambda s: c.out_double[index]
        if name.startswith("input_int_register_"):
            index = int(name.rsplit("_", 1)[1])
            return lambda s: c.in_int[index]
        if name.startswith("input_double_register_"):
            index = int(name.rsplit("_", 1)[1])
            return lambda s: c.in_double[index]
        typ = OUTPUT_FIELDS[name]
        default = {"VECTOR6D": [0.0] * 6, "VECTOR3D": [0.0] * 3, "VECTOR6INT32": [0] * 6,
                   "VECTOR6UINT32": [0] * 6, "DOUBLE": 0.0, "BOOL": False}.get(typ, 0)
        return lambda s: s.get(name, default)

    @staticmethod
    def _send(sock: socket.socket, kind: int, payload: bytes) -> None:
        sock.sendall(struct.pack(">HB", len(payload) + 3, kind) + payload)


class InputOwnership:
    """Input fields belong to one RTDE connection at a time (a real controller answers IN_USE)."""

    def __init__(self) -> None:
        self._owners: dict[str, object] = {}
        self._lock = threading.Lock()

    def claim(self, owner: object, names: list[str]) -> bool:
        with self._lock:
            if any(self._owners.get(n, owner) is not owner for n in names):
                return False
            for n in names:
                self._owners[n] = owner
            return True

    def taken_by_other(self, owner: object, name: str) -> bool:
        with self._lock:
            return self._owners.get(name, owner) is not owner

    def release(self, owner: object) -> None:
        with self._lock:
            for n in [n for n, o in self._owners.items() if o is owner]:
                del self._owners[n]


# --------------------------------------------------------------------------------------- dashboard
class DashboardHandler:
    """Line-based dashboard server with the answers of PolyScope 5."""

    def __init__(self, controller: URController) -> None:
        self.c = controller

    def __call__(self, sock: socket.socket, server: TcpServer) -> None:
        sock.sendall(b"Connected: Universal Robots Dashboard Server\n")
        buffer = b""
        while server.running.is_set():
            ready, _, _ = select.select([sock], [], [], 0.2)
            if not ready:
                continue
            chunk = sock.recv(4096)
            if not chunk:
                return
            buffer += chunk
            while b"\n" in buffer:
                line, buffer = buffer.split(b"\n", 1)
                command = line.decode("utf-8", errors="replace").strip()
                armed = self.c.faults.peek(FaultKind.SLOW)
                if armed is not None:
                    time.sleep(float(armed.params.get("seconds", 0.5)))
                reply, close = self.answer(command)
                sock.sendall(reply.encode() + b"\n")
                if close:
                    return

    def answer(self, command: str) -> tuple[str, bool]:
        c = self.c
        version = ".".join(str(x) for x in c.config.version)
        lower = command.lower()
        if lower == "polyscopeversion":
            return f"URSoftware {version} (Mar 01 2024)", False
        if lower == "get serial number":
            return c.config.serial_number, False
        if lower == "is in remote control":
            return "true" if c.config.remote_control else "false", False
        if lower == "get robot model":
            return "UR5", False
        if lower == "stop":
            c.stop_program("dashboard stop")
            return "Stopped", False
        if lower == "play":
            return "Failed to execute: play", False
        if lower == "pause":
            return "Failed to execute: pause", False
        if lower == "running":
            return f"Program running: {'true' if c.runtime_state == RUNTIME_PLAYING else 'false'}", False
        if lower == "programstate":
            playing = c.runtime_state == RUNTIME_PLAYING
            return ("PLAYING rtde_control" if playing else "STOPPED <unnamed>"), False
        if lower == "robotmode":
            return {3: "Robotmode: POWER_OFF", 7: "Robotmode: RUNNING"}.get(c.robot_mode, "Robotmode: IDLE"), False
        if lower in ("safetymode", "safetystatus"):
            prefix = "Safetymode" if lower == "safetymode" else "Safetystatus"
            if c.safety_bits & SAFETY_BIT_ESTOP:
                return f"{prefix}: ROBOT_EMERGENCY_STOP", False
            if c.safety_bits & SAFETY_BIT_PROTECTIVE:
                return f"{prefix}: PROTECTIVE_STOP", False
            return f"{prefix}: NORMAL", False
        if lower == "unlock protective stop":
            if c.safety_bits & SAFETY_BIT_PROTECTIVE:
                c.clear_safety()
                return "Protective stop releasing", False
            return (
                "Cannot unlock protective stop until 5s after occurrence. "
                "Always inspect cause of protective stop before unlocking",
                False,
            )
        if lower in DASHBOARD_FIXED_REPLIES:
            return DASHBOARD_FIXED_REPLIES[lower], False
        if lower.startswith("load "):
            return f"File not found: {command[5:]}", False
        if lower.startswith("popup "):
            return "showing popup", False
        if lower.startswith("addtolog "):
            return "Added log message", False
        if lower == "quit":
            return "Disconnected", True
        c.log(f"dashboard: unknown command {command!r}")
        return f"could not understand: '{command}'", False


# --------------------------------------------------------------------------------------- script
class ScriptHandler:
    """Port 30003: collects URScript programs; runs ur_rtde's control script, logs anything else."""

    def __init__(self, controller: URController) -> None:
        self.c = controller
        self.programs_received = 0

    def __call__(self, sock: socket.socket, server: TcpServer) -> None:
        buffer = ""
        while server.running.is_set():
            ready, _, _ = select.select([sock], [], [], 0.2)
            if not ready:
                continue
            chunk = sock.recv(65536)
            if not chunk:
                return
            buffer += chunk.decode("utf-8", errors="replace")
            buffer = self._consume(buffer)

    def _consume(self, buffer: str) -> str:
        """Take every complete program (``def``/``sec`` … top-level ``end``) or loose line out."""
        while True:
            lines = buffer.split("\n")
            if len(lines) < 2:
                return buffer
            first = lines[0]
            if first.startswith(("def ", "sec ")):
                for index, line in enumerate(lines[1:-1], start=1):
                    if line.rstrip() == "end":
                        program = "\n".join(lines[: index + 1]) + "\n"
                        buffer = "\n".join(lines[index + 1:])
                        self._run(program)
                        break
                else:
                    return buffer
            else:
                buffer = "\n".join(lines[1:])
                if first.strip():
                    self.c.log(f"script port: loose statement ignored: {first.strip()[:80]!r}")

    def _run(self, program: str) -> None:
        self.programs_received += 1
        offsets = recognise_control_script(program)
        if offsets is None:
            header = program.split("\n", 1)[0]
            self.c.log(f"script port: program {header!r} ({len(program)} chars) is not emulated; ignored")
            return
        if self.c.safety_bits & (SAFETY_BIT_PROTECTIVE | SAFETY_BIT_ESTOP):
            self.c.log("script port: control script refused while the robot is in a safety stop")
            return
        ControlScript(self.c, *offsets).start()
