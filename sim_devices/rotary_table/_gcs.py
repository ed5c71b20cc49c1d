"""The rotary table's GCS face: a PI GCS 2.0 style line protocol, served on a pty (here) and on TCP
(``_gcs_tcp.py``), as a PI controller offers both (RS-232 and TCP port 50000).

One axis, identifier ``"1"``, units degrees. Commands end with LF; set commands are silent, queries
answer one line per item and every line but the last ends with ``" \\n"`` (the GCS multi-line rule).
Errors are latched and read (and cleared) with ``ERR?``; only the last error is kept.

Supported: ``*IDN?``, ``CSV?`` (``2.0``), ``ERR?``, ``SAI?``, ``HLP?``, ``MOV``, ``MVR``, ``POS?``,
``MOV?`` (commanded target), ``ONT?``, ``FRF``, ``FRF?``, ``STP``, ``HLT``, ``VEL``, ``VEL?``, ``SVO``,
``SVO?``, ``TMN?``, ``TMX?``, and the single-byte queries ``#5`` (moving), ``#7`` (ready), ``#24`` (stop).

The controller powers on with the servo off and the axis unreferenced: ``MOV``/``MVR`` latch error 5
until ``SVO 1 1`` and ``FRF 1`` have been sent (``FRF`` itself needs the servo on). Targets beyond the
table's soft limits (``TMN?``/``TMX?``, the physics' ``travel_min``/``travel_max``) latch error 7.

An armed ``exception`` fault (param ``code``, default 1) makes the next line fail with that error
code: a set command is not executed, a query gets no answer (``ERR?`` itself is never hit).
"""

from __future__ import annotations

import math
import os
import select
import threading
from collections.abc import Callable

from sim_devices._pty import PtyRelay, line_framer
from sim_devices.faults import FaultKind, FaultPlan
from sim_devices.rotary_table._physics import CommandRefused, TablePhysics

AXIS = "1"
SINGLE_BYTE_COMMANDS = (b"\x05", b"\x07", b"\x18")  # #5, #7, #24 sent as one byte, without LF

# PI GCS error codes used here (the numbers and meanings of PI's controllers).
ERRORS = {
    0: "No error",
    1: "Parameter syntax error",
    2: "Unknown command",
    5: "Unallowable move attempted on unreferenced axis, or move attempted with servo off",
    7: "Position out of limits",
    10: "Controller was stopped by command",
    15: "Invalid axis identifier",
    17: "Parameter out of range",
    1024: "Motion error: position error too large, servo is switched off automatically",
}


class GcsError(Exception):
    def __init__(self, code: int) -> None:
        self.code = code
        super().__init__(ERRORS.get(code, str(code)))


def split_commands(buffer: bytes) -> tuple[list[str | None], bytes]:
    """The complete commands at the start of ``buffer`` and the incomplete rest.

    A command is a single-byte query or a line ended by LF; a line that is not ASCII is ``None``
    (the controller latches a syntax error for it).
    """
    commands: list[str | None] = []
    while True:
        if buffer[:1] in SINGLE_BYTE_COMMANDS:
            commands.append(chr(buffer[0]))
            buffer = buffer[1:]
            continue
        index = buffer.find(b"\n")
        if index < 0:
            return commands, buffer
        raw, buffer = buffer[:index], buffer[index + 1:]
        try:
            commands.append(raw.decode("ascii"))
        except UnicodeDecodeError:
            commands.append(None)


def corrupt_middle(reply: bytes) -> bytes:
    """A parity error on the line: one character in the middle of the answer is flipped."""
    if len(reply) < 3:
        return reply
    index = len(reply) // 2
    return reply[:index] + bytes([reply[index] ^ 0x40 | 0x80]) + reply[index + 1:]


class GcsController:
    """Parses GCS lines and drives the physics. Pure logic: ``handle(line) -> answer bytes``."""

    def __init__(self, physics: TablePhysics, faults: FaultPlan, idn: str = "PI-style,SIM-RT-1,0815,2.0.0") -> None:
        self.physics = physics
        self.faults = faults
        self.idn = idn
        self.error = 0
        self._quantum_deg = 360.0 / physics.config.counts_per_rev
        self._lock = threading.Lock()

    def _deg(self, counts: int) -> float:
        return counts * self._quantum_deg

    def handle(self, line: str | None) -> bytes:
        """The answer to one command line (``None``: a line that was not ASCII), b"" for none."""
        with self._lock:
            if line is None:
                self.error = 1
                return b""
            line = line.strip()
            if not line:
                return b""
            fault = None if line.upper() == "ERR?" else self.faults.take(FaultKind.EXCEPTION)
            if fault is not None:  # ERR? is how the error is read, so it never fails itself
                self.error = int(fault.params.get("code", 1))
                return b""
            try:
                answers = self._dispatch(line)
            except GcsError as exc:
                self.error = exc.code
                return b""
            if not answers:
                return b""
            return (" \n".join(answers) + "\n").encode("latin-1")

    # ----------------------------------------------------------------------------- parsing
    def _dispatch(self, line: str) -> list[str]:
        if line in ("#5", "\x05"):
            return [str(1 if self.physics.status()["moving"] else 0)]
        if line in ("#7", "\x07"):
            return ["\xb1" if not self.physics.status()["moving"] else "\xb0"]
        if line in ("#24", "\x18"):
            self._stop()
            return []
        command, *args = line.split()
        command = command.upper()
        handler: Callable[[list[str]], list[str]] | None = getattr(self, "_cmd_" + _mangle(command), None)
        if handler is None:
            raise GcsError(2)
        return handler(args)

    def _axes(self, args: list[str]) -> list[str]:
        axes = args or [AXIS]
        for axis in axes:
            if axis != AXIS:
                raise GcsError(15)
        return axes

    def _pairs(self, args: list[str]) -> list[tuple[str, float]]:
        if not args or len(args) % 2:
            raise GcsError(1)
        pairs = []
        for axis, value in zip(args[::2], args[1::2]):
            self._axes([axis])
            try:
                number = float(value)
            except ValueError:
                raise GcsError(1) from None
            if not math.isfinite(number):
                raise GcsError(1)
            pairs.append((axis, number))
        return pairs

    def _counts(self, degrees: float) -> int:
        if abs(degrees) > 1e6:  # far beyond any travel; also keeps the integer conversion sane
            raise GcsError(7)
        return int(round(degrees / self._quantum_deg))

    @staticmethod
    def _refuse(exc: CommandRefused) -> GcsError:
        return GcsError({"alarm": 1024, "travel": 7, "value": 17}.get(exc.reason, 5))

    # ----------------------------------------------------------------------------- commands
    def _cmd_IDN_Q(self, args: list[str]) -> list[str]:  # *IDN?
        return [self.idn]

    def _cmd_CSV_Q(self, args: list[str]) -> list[str]:
        return ["2.0"]

    def _cmd_ERR_Q(self, args: list[str]) -> list[str]:
        code, self.error = self.error, 0
        return [str(code)]

    def _cmd_SAI_Q(self, args: list[str]) -> list[str]:
        return [AXIS]

    def _cmd_HLP_Q(self, args: list[str]) -> list[str]:
        return ["The following commands are valid:"] + [
            f"{name} {text}" for name, text in (
                ("*IDN?", "Get Device Identification"), ("CSV?", "Get Current Syntax Version"),
                ("ERR?", "Get Error Number"), ("MOV", "Set Target Position"), ("MVR", "Set Target Relative"),
                ("POS?", "Get Real Position"), ("ONT?", "Get On Target State"), ("FRF", "Reference Axis"),
                ("STP", "Stop All Axes"), ("HLT", "Halt Motion Smoothly"), ("VEL", "Set Velocity"),
            )
        ]

    def _cmd_MOV(self, args: list[str]) -> list[str]:
        for _, degrees in self._pairs(args):
            try:
                self.physics.move_to_counts(self._counts(degrees))
            except CommandRefused as exc:
                raise self._refuse(exc) from None
        return []

    def _cmd_MVR(self, args: list[str]) -> list[str]:
        for _, degrees in self._pairs(args):
            target = self.physics.status()["target_counts"] * self._quantum_deg + degrees
            try:
                self.physics.move_to_counts(self._counts(target))
            except CommandRefused as exc:
                raise self._refuse(exc) from None
        return []

    def _cmd_POS_Q(self, args: list[str]) -> list[str]:
        return [f"{axis}={self._deg(self.physics.read_counts()):.9f}" for axis in self._axes(args)]

    def _cmd_MOV_Q(self, args: list[str]) -> list[str]:
        return [f"{axis}={self._deg(self.physics.status()['target_counts']):.9f}" for axis in self._axes(args)]

    def _cmd_ONT_Q(self, args: list[str]) -> list[str]:
        return [f"{axis}={int(self.physics.status()['in_position'])}" for axis in self._axes(args)]

    def _cmd_FRF(self, args: list[str]) -> list[str]:
        self._axes(args)
        try:
            self.physics.home()
        except CommandRefused as exc:
            raise self._refuse(exc) from None
        return []

    def _cmd_FRF_Q(self, args: list[str]) -> list[str]:
        return [f"{axis}={int(self.physics.status()['homed'])}" for axis in self._axes(args)]

    def _stop(self) -> None:
        self.physics.stop()
        self.error = 10  # PI: "controller was stopped by command"

    def _cmd_STP(self, args: list[str]) -> list[str]:
        self._stop()
        return []

    def _cmd_HLT(self, args: list[str]) -> list[str]:
        self._axes(args)
        self._stop()
        return []

    def _cmd_VEL(self, args: list[str]) -> list[str]:
        for _, degrees_per_s in self._pairs(args):
            try:
                self.physics.set_speed(math.radians(degrees_per_s))
            except CommandRefused:
                raise GcsError(17) from None
        return []

    def _cmd_VEL_Q(self, args: list[str]) -> list[str]:
        return [f"{axis}={math.degrees(self.physics.speed):.9f}" for axis in self._axes(args)]

    def _cmd_SVO(self, args: list[str]) -> list[str]:
        for _, state in self._pairs(args):
            if state not in (0.0, 1.0):
                raise GcsError(17)
            if state:
                self.physics.alarm_reset()  # servo on after a motion error clears it
            self.physics.enable(bool(state))
        return []

    def _cmd_SVO_Q(self, args: list[str]) -> list[str]:
        status = self.physics.status()  # a motion error switches the servo off (PI behaviour)
        return [f"{axis}={int(status['enabled'] and not status['alarms'])}" for axis in self._axes(args)]

    def _cmd_TMN_Q(self, args: list[str]) -> list[str]:
        return [f"{axis}={math.degrees(self.physics.config.travel_min):.9f}" for axis in self._axes(args)]

    def _cmd_TMX_Q(self, args: list[str]) -> list[str]:
        return [f"{axis}={math.degrees(self.physics.config.travel_max):.9f}" for axis in self._axes(args)]


def _mangle(command: str) -> str:
    return command.replace("*", "").replace("?", "_Q")


class GcsTableTwin:
    """The GCS controller served on a pty, behind a fault relay. ``start()`` → ``{"gcs_port": path}``."""

    def __init__(self, physics: TablePhysics, *, seed: int = 0) -> None:
        self.faults = FaultPlan()
        self.controller = GcsController(physics, self.faults)
        self._seed = seed
        self._relay: PtyRelay | None = None
        self._fd = -1
        self._wake_r = self._wake_w = -1
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def start(self) -> dict[str, str]:
        self._relay = PtyRelay(self.faults, framer=line_framer, corrupt=corrupt_middle, seed=self._seed,
                               name="gcs relay").start()
        self._fd = os.open(self._relay.device_path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        self._wake_r, self._wake_w = os.pipe()
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name="gcs table twin", daemon=True)
        self._thread.start()
        return {"gcs_port": self._relay.host_path}

    def _serve(self) -> None:
        buffer = b""
        while not self._stop.is_set():
            readable, _, _ = select.select([self._fd, self._wake_r], [], [], 0.5)
            if self._wake_r in readable:
                break
            if self._fd not in readable:
                continue
            try:
                data = os.read(self._fd, 4096)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                break
            commands, buffer = split_commands(buffer + data)
            for command in commands:
                self._answer(command)

    def _answer(self, line: str | None) -> None:
        answer = self.controller.handle(line)
        if answer:
            try:
                os.write(self._fd, answer)
            except OSError:
                pass

    def stop(self) -> None:
        self._stop.set()
        if self._wake_w >= 0:
            os.write(self._wake_w, b"x")
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        for fd in (self._fd, self._wake_r, self._wake_w):
            if fd >= 0:
                os.close(fd)
        self._fd = self._wake_r = self._wake_w = -1
        if self._relay is not None:
            self._relay.stop()
            self._relay = None
