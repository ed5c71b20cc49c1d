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
    CycleState,
    URController,
)
from sim_devices.ur._fields import INPUT_FIELDS, OUTPUT_FIELDS, Recipe, parse_names
from sim_devices.ur._script import ControlScript, recognise_control_script
from sim_devices.ur._urscript import CustomScript

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

    def signal_stop(self) -> None:
        """Stop accepting and drop the connections, without waiting for the accept loop to end."""
        self.running.clear()
        if self._listener is not None:
            self._listener.close()
        self.drop_connections()

    def stop(self) -> None:
        self.signal_stop()
        if self._thread is not None:
            self._thread.join(2.0)  # the accept loop sees the flag within its 0.2 s accept timeout

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


class RTDEConnection:
    """One RTDE client connection's outgoing side: replies from its handler thread and data packages
    from the controller's cycle thread go through one buffer under one lock, never blocking either
    thread (a client that stops reading is dropped once ``MAX_PENDING`` bytes are waiting)."""

    MAX_PENDING = 1 << 20

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.lock = threading.Lock()
        self.output: Recipe | None = None
        self.getters: list[Callable[[dict[str, Any]], object]] = []
        self.decimation = 1
        self.started = False
        self.dead = False
        self.packages = 0  # data packages handed to the socket (or its queue)
        self.backlog_peak = 0  # most bytes ever waiting for a client that reads too slowly
        self._pending = b""

    def reply(self, kind: int, payload: bytes) -> None:
        """A setup reply (handler thread), in order with the data packages."""
        with self.lock:
            self._write(struct.pack(">HB", len(payload) + 3, kind) + payload)

    def offer(self, state: CycleState, send_data: bool) -> None:
        """The cycle thread: flush what is waiting, then this cycle's data package if one is due."""
        with self.lock:
            if self.dead:
                return
            if send_data and self.started and self.output is not None and state.cycle % self.decimation == 0:
                fields = state.fields
                payload = self.output.pack([get(fields) for get in self.getters])
                self._write(struct.pack(">HB", len(payload) + 3, U) + payload)
                self.packages += 1
            elif self._pending:
                self._write(b"")

    def _write(self, data: bytes) -> None:
        self._pending += data
        try:
            sent = self.sock.send(self._pending, socket.MSG_DONTWAIT)
        except BlockingIOError:
            sent = 0
        except OSError:
            self._drop()
            return
        self._pending = self._pending[sent:]
        self.backlog_peak = max(self.backlog_peak, len(self._pending))
        if len(self._pending) > self.MAX_PENDING:
            self._drop()

    def _drop(self) -> None:
        self.dead = True
        self._pending = b""
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass


class RTDEStreams:
    """Every RTDE connection of the twin, fed with each cycle's one ``CycleState`` by the controller."""

    def __init__(self, controller: URController) -> None:
        self.c = controller
        self._connections: list[RTDEConnection] = []
        self._lock = threading.Lock()
        self.packages = 0
        controller.add_cycle_listener(self.on_cycle, needs_cycles=lambda: bool(self._connections))

    def add(self, connection: RTDEConnection) -> None:
        with self._lock:
            self._connections = [*self._connections, connection]
        self.c.wake_cycle()  # its replies go out with the cycles: no quiet wait now

    def remove(self, connection: RTDEConnection) -> None:
        with self._lock:
            self._connections = [c for c in self._connections if c is not connection]

    def stats(self) -> list[dict[str, int]]:
        """Per connection: data packages sent and the peak backlog (bytes a slow reader left queued)."""
        return [{"packages": c.packages, "backlog_peak": c.backlog_peak, "started": int(c.started)}
                for c in self._connections]

    def on_cycle(self, state: CycleState) -> None:
        c = self.c
        connections = self._connections
        streaming = any(conn.started for conn in connections)
        now = time.monotonic()
        send_data = now >= c.stream_stall_until
        if send_data and streaming:
            stall = c.faults.take(FaultKind.STALL)
            if stall is not None:
                seconds = float(stall.params.get("seconds", 3.0))
                c.stream_stall_until = now + seconds
                c.log(f"RTDE stream stalled for {seconds} s (injected)")
                send_data = False
        for connection in connections:
            connection.offer(state, send_data)


class RTDEHandler:
    """One RTDE session: version handshake, recipes, start/pause and input packages. The data
    packages are sent by the controller's cycle (``RTDEStreams``)."""

    def __init__(self, controller: URController, registry: InputOwnership, streams: RTDEStreams) -> None:
        self.c = controller
        self.registry = registry
        self.streams = streams

    def __call__(self, sock: socket.socket, server: TcpServer) -> None:
        c = self.c
        connection = RTDEConnection(sock)
        inputs: dict[int, Recipe] = {}
        owner = object()
        self.streams.add(connection)
        try:
            while server.running.is_set() and not connection.dead:
                ready, _, _ = select.select([sock], [], [], 0.2)
                if not ready:
                    continue
                size, kind = struct.unpack(">HB", _recv_exact(sock, 3, server.running))
                payload = _recv_exact(sock, size - 3, server.running) if size > 3 else b""
                if kind != U:
                    self._setup_delay()
                if kind == V:
                    connection.reply(V, struct.pack(">B", 1))
                elif kind == v:
                    connection.reply(v, struct.pack(">IIII", *c.config.version))
                elif kind == O:
                    frequency = struct.unpack(">d", payload[:8])[0]
                    output = Recipe(1, parse_names(payload[8:]), OUTPUT_FIELDS)
                    cap = c.config.max_stream_rate
                    rate = min(frequency, cap) if cap else frequency
                    with connection.lock:
                        connection.output = output if output.valid else None
                        connection.getters = [field_getter(name) for name in output.names] if output.valid else []
                        connection.decimation = max(1, round(1.0 / (c.period * max(rate, 1.0))))
                    connection.reply(O, output.reply_payload())
                elif kind == I:
                    recipe = Recipe(len(inputs) + 1, parse_names(payload), INPUT_FIELDS)
                    if recipe.valid and not self.registry.claim(owner, recipe.names):
                        recipe.types = ["IN_USE" if self.registry.taken_by_other(owner, n) else t
                                        for n, t in zip(recipe.names, recipe.types)]
                        connection.reply(I, struct.pack(">B", 0) + ",".join(recipe.types).encode())
                        continue
                    if recipe.valid:
                        inputs[recipe.id] = recipe
                    connection.reply(I, recipe.reply_payload())
                elif kind == S:
                    ok = connection.output is not None
                    connection.reply(S, struct.pack(">B", 1 if ok else 0))  # the reply BEFORE the first data
                    connection.started = ok
                elif kind == P:
                    connection.started = False
                    connection.reply(P, struct.pack(">B", 1))
                elif kind == U and payload:
                    input_recipe = inputs.get(payload[0])
                    if input_recipe is not None:
                        c.set_inputs(input_recipe.unpack(payload[1:]))
        finally:
            self.streams.remove(connection)
            self.registry.release(owner)

    def _setup_delay(self) -> None:
        armed = self.c.faults.peek(FaultKind.SLOW)
        if armed is not None:
            time.sleep(float(armed.params.get("seconds", 0.5)))


def field_getter(name: str) -> Callable[[dict[str, Any]], object]:
    """How to read output field ``name`` from a cycle's fields (registers from their copies)."""
    for prefix, bank in (("output_int_register_", "out_int"), ("output_double_register_", "out_double"),
                         ("input_int_register_", "in_int"), ("input_double_register_", "in_double")):
        if name.startswith(prefix):
            index = int(name.rsplit("_", 1)[1])

            def register(f: dict[str, Any], bank: str = bank, index: int = index) -> object:
                return f[bank][index]

            return register
    typ = OUTPUT_FIELDS[name]
    default = {"VECTOR6D": [0.0] * 6, "VECTOR3D": [0.0] * 3, "VECTOR6INT32": [0] * 6,
               "VECTOR6UINT32": [0] * 6, "DOUBLE": 0.0, "BOOL": False}.get(typ, 0)
    return lambda f: f.get(name, default)


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
            return c.config.robot_model, False
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
            # PolyScope refuses for 5 s after the stop (and, as the twin has always answered, when
            # there is no protective stop to unlock).
            if c.safety_bits & SAFETY_BIT_PROTECTIVE and c.unlock_wait() <= 0:
                c.clear_safety()
                return "Protective stop releasing", False
            delay = f"{c.config.protective_stop_unlock_delay:g}"
            return (
                f"Cannot unlock protective stop until {delay}s after occurrence. "
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
        custom = CustomScript.from_program(self.c, program) if offsets is None else None
        if offsets is None and custom is None:
            header = program.split("\n", 1)[0]
            self.c.log(f"script port: program {header!r} ({len(program)} chars) is not emulated; ignored")
            return
        if self.c.safety_bits & (SAFETY_BIT_PROTECTIVE | SAFETY_BIT_ESTOP):
            self.c.log("script port: program refused while the robot is in a safety stop")
            return
        if custom is not None:
            custom.start()
        else:
            assert offsets is not None
            ControlScript(self.c, *offsets, program=program).start()
