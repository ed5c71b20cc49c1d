"""``GcsTable``: a rotary stage behind a PI-GCS-2.0-style controller, on a serial line (pyserial,
adapter ``gcs_serial``) or on the controller's TCP interface (adapter ``gcs_tcp``; PI: port 50000).
Both share everything here; only the byte link differs (``_gcs_link.py``).

Line protocol: commands end with LF; set commands are silent and are followed by ``ERR?`` (a
nonzero, latched error code becomes ``TableFault``, or ``CommandRefused`` for a refused value:
7 out of limits, 17 out of range); queries answer one line per item, every line but the last ending
in ``" \\n"``. Degrees on the wire, radians in the API.

Opening: ``CSV?`` (GCS 2.0), ``*IDN?``, ``ERR?`` (clears a latched error), then unless
``reference_on_open`` is off what a PI controller needs before it moves: ``SVO <axis> 1`` if the
servo is off, and ``FRF <axis>`` if the axis is unreferenced, waited for within
``servo_timeout``/``reference_timeout``.

Robustness: the input is flushed before every request; a query that gets no answer within
``timeout`` is a ``DeviceTimeout``; an answer that is not printable ASCII, does not parse, or stops
without its LF is a ``ProtocolError``. Both are retried ``retries`` times (after a guard wait for a
late answer, which the flush then discards). On TCP a lost connection is re-opened and a query
retried. Set commands are never resent (``MVR`` twice would move twice); only their ``ERR?`` is.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Callable
from typing import Any

from drivers._errors import DeviceConnectionError, DeviceError, DeviceTimeout, MotionRefused, ProtocolError
from drivers.rotary_table._gcs_link import GcsLink, SerialLink, TcpLink
from drivers.rotary_table._interface import CommandRefused, TableFault, TableState
from drivers.rotary_table._settings import GcsSerialSettings, GcsSettings

PI_ERRORS = {
    1: "parameter syntax error",
    2: "unknown command",
    5: "move on an unreferenced axis or with servo off",
    7: "position out of limits",
    10: "controller was stopped by command",
    15: "invalid axis identifier",
    17: "parameter out of range",
    1024: "motion error (position error too large, servo switched off)",
}
STOPPED_BY_COMMAND = 10
REFUSED_VALUES = (7, 17)  # the controller refused a value; nothing moved, nothing is wrong with it
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


class GcsTable:
    """One axis of a GCS 2.0 controller.

    Parameters
    ----------
    settings : GcsSerialSettings or GcsTcpSettings
        Serial port (or pyserial URL) and baud rate, or host and port; axis, answer timeout,
        retries, poll interval, and what ``open()`` does (``reference_on_open`` and its timeouts).
    name : str
        Device name for errors.
    """

    def __init__(self, settings: GcsSettings, *, name: str = "rotary_table") -> None:
        self.name = name
        self.settings = settings
        self.axis = settings.axis
        self.timeout = settings.timeout
        self.retries = settings.retries
        self.poll_interval = settings.poll_interval
        self._link: GcsLink
        if isinstance(settings, GcsSerialSettings):
            self.port = settings.port
            self._link = SerialLink(settings.port, settings.baudrate, settings.timeout)
        else:
            self.port = f"{settings.host}:{settings.port}"
            self._link = TcpLink(settings.host, settings.port, settings.timeout)
        self.identity = ""

    # ----------------------------------------------------------------------------- connection
    def open(self) -> None:
        """Connect, check the GCS version, read the identity, clear a latched error; then (unless
        ``reference_on_open`` is off) servo on and the reference move if the axis is unreferenced.

        Raises
        ------
        DeviceConnectionError, DeviceTimeout, ProtocolError
            The controller cannot be reached, does not answer, or does not speak GCS 2.0.
        TableFault
            The controller refused the servo-on or the reference move (its GCS error).
        DeviceTimeout
            The servo did not come on within ``servo_timeout``, or the reference move did not end
            within ``reference_timeout`` (the operation names which).
        """
        self.close()
        self._connect("open")
        try:
            version = self._query("CSV?")[0].strip()
            if version not in ("2", "2.0"):
                raise ProtocolError(self.name, "CSV?", f"controller speaks GCS {version!r}, expected 2.0")
            self.identity = self._query("*IDN?")[0].strip()
            self._error_code()  # clear whatever was latched before we came
            if self.settings.reference_on_open:
                self._make_ready()
        except DeviceError:
            self.close()
            raise

    def _connect(self, operation: str) -> None:
        try:
            self._link.open()
        except (OSError, ValueError) as exc:
            raise DeviceConnectionError(self.name, f"{operation} {self._link.description}", str(exc)) from None

    def _make_ready(self) -> None:
        """What a PI controller needs before it moves: servo on, then the reference move."""
        settings = self.settings
        if not self._axis_flag("SVO?"):
            self._command(f"SVO {self.axis} 1", "open: servo on (SVO)")
            self._wait(lambda: self._axis_flag("SVO?"), settings.servo_timeout, "open: servo on (SVO)",
                       "the servo is not on")
        if not self._axis_flag("FRF?"):
            self.home(settings.reference_timeout, operation="open: reference move (FRF)")

    def close(self) -> None:
        self._link.close()

    def __enter__(self) -> GcsTable:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------------------- line I/O
    def _ensure_link(self, operation: str) -> None:
        if self._link.is_open:
            return
        if not self._link.reconnectable:
            raise DeviceConnectionError(self.name, operation, "not open (call open() first)")
        self._connect(f"{operation}: reconnect")  # a TCP connection that was lost

    def _send(self, line: str, operation: str) -> None:
        self._ensure_link(operation)
        try:
            self._link.discard_input()  # a late answer to an earlier request must not pass for this one
            self._link.write(line.encode("ascii") + b"\n")
        except OSError as exc:
            raise DeviceConnectionError(self.name, operation, f"write failed: {exc}") from None

    def _read_answer(self, operation: str) -> list[str]:
        deadline = time.monotonic() + self.timeout
        lines: list[str] = []
        partial = b""
        while True:
            if deadline - time.monotonic() <= 0:
                break
            try:
                chunk = self._link.read_line(deadline)
            except OSError as exc:
                raise DeviceConnectionError(self.name, operation, f"read failed: {exc}") from None
            partial += chunk
            if not partial.endswith(b"\n"):
                continue
            if any(b < 0x20 or b > 0x7E for b in partial[:-1]):
                raise ProtocolError(self.name, operation, f"non-ASCII bytes in the answer: {partial!r}")
            text = partial.decode("ascii")
            partial = b""
            if text.endswith(" \n"):
                lines.append(text[:-2])
                continue
            lines.append(text[:-1])
            return lines
        got = b"".join(line.encode() + b" \n" for line in lines) + partial
        if got:
            raise ProtocolError(
                self.name, operation, f"answer cut short (no final LF within {self.timeout} s): {got!r}"
            )
        raise DeviceTimeout(self.name, operation, f"no answer within {self.timeout} s")

    def _query(self, line: str, pattern: str | None = None) -> list[str]:
        """Send a query, return its lines (each matching ``pattern`` if given); bounded retries."""
        last: DeviceError | None = None
        for _attempt in range(self.retries + 1):
            try:
                self._send(line, line)
                lines = self._read_answer(line)
                if pattern is not None:
                    for item in lines:
                        if not re.fullmatch(pattern, item):
                            raise ProtocolError(self.name, line, f"unexpected answer {item!r}")
                return lines
            except DeviceTimeout as exc:
                last = exc
                time.sleep(self.timeout)  # guard: a late answer lands now and is flushed by the next send
            except ProtocolError as exc:
                last = exc
                time.sleep(min(self.timeout, 0.05))  # let the rest of a garbled answer drain
            except DeviceConnectionError as exc:
                if not self._link.reconnectable:
                    raise
                last = exc  # a query is safe to resend on a new connection
                self._link.close()
                time.sleep(min(self.timeout, 0.05))
        assert last is not None
        if isinstance(last, DeviceTimeout) and line != "ERR?":
            code = self._error_code(raise_on_failure=False)
            if code:  # the controller refused the query: that is the real cause
                raise TableFault(self.name, line, f"GCS error {code}: {PI_ERRORS.get(code, 'see the manual')}")
        raise last

    def _axis_value(self, query: str) -> str:
        answer = self._query(f"{query} {self.axis}", rf"{re.escape(self.axis)}=\S+")
        if len(answer) != 1:
            raise ProtocolError(self.name, query, f"expected one line for axis {self.axis}, got {answer!r}")
        return answer[0].split("=", 1)[1]

    def _axis_number(self, query: str) -> float:
        value = self._axis_value(query)
        if not re.fullmatch(_NUMBER, value):
            raise ProtocolError(self.name, query, f"not a number: {value!r}")
        return float(value)

    def _axis_flag(self, query: str) -> bool:
        value = self._axis_value(query)
        if value not in ("0", "1"):
            raise ProtocolError(self.name, query, f"expected 0 or 1, got {value!r}")
        return value == "1"

    def _error_code(self, raise_on_failure: bool = True) -> int:
        try:
            answer = self._query("ERR?", r"-?\d+")
        except DeviceError:
            if raise_on_failure:
                raise
            return 0
        return int(answer[0])

    def _command(self, line: str, operation: str, tolerate: tuple[int, ...] = ()) -> None:
        self._send(line, operation)
        code = self._error_code()
        if code and code not in tolerate:
            text = f"GCS error {code}: {PI_ERRORS.get(code, 'see the manual')}"
            if code in REFUSED_VALUES:
                raise CommandRefused(self.name, operation, text)
            raise TableFault(self.name, operation, text)

    # ----------------------------------------------------------------------------- table API
    def _set_speed(self, speed: float | None, operation: str) -> None:
        if speed is None:
            return
        if not math.isfinite(speed) or speed <= 0:
            raise MotionRefused(self.name, operation, f"speed {speed!r} rad/s is not a usable positive speed")
        self._command(f"VEL {self.axis} {math.degrees(speed):.9f}", operation)

    def move_absolute(self, angle: float, speed: float | None = None) -> None:
        operation = f"move_absolute({angle!r})"
        if not math.isfinite(angle):
            raise MotionRefused(self.name, operation, "target angle is not a finite number")
        self._set_speed(speed, operation)
        self._command(f"MOV {self.axis} {math.degrees(angle):.9f}", operation)

    def move_relative(self, delta: float, speed: float | None = None) -> None:
        operation = f"move_relative({delta!r})"
        if not math.isfinite(delta):
            raise MotionRefused(self.name, operation, "distance is not a finite number")
        self._set_speed(speed, operation)
        self._command(f"MVR {self.axis} {math.degrees(delta):.9f}", operation)

    def _wait(self, done: Callable[[], bool], timeout: float, operation: str,
              not_yet: str = "not on target") -> None:
        deadline = time.monotonic() + timeout
        polls = 0
        while True:
            if done():
                return
            polls += 1
            if polls % 10 == 0:  # a motion error leaves ONT? at 0 for ever: look for it now and then
                code = self._error_code()
                if code:
                    raise TableFault(self.name, operation, f"GCS error {code}: {PI_ERRORS.get(code, 'see the manual')}")
            if time.monotonic() > deadline:
                raise DeviceTimeout(self.name, operation, f"{not_yet} after {timeout} s")
            time.sleep(self.poll_interval)

    def wait_in_position(self, timeout: float = 30.0) -> float:
        self._wait(lambda: self._axis_flag("ONT?"), timeout, "wait_in_position")
        return self.position()

    def home(self, timeout: float = 30.0, *, operation: str = "home (FRF)") -> None:
        """Reference move to the reference mark (the true zero); waits until referenced and on target."""
        self._command(f"FRF {self.axis}", operation)
        self._wait(lambda: self._axis_flag("FRF?") and self._axis_flag("ONT?"), timeout, operation,
                   "not referenced")

    def position(self) -> float:
        return math.radians(self._axis_number("POS?"))

    def stop(self) -> None:
        self._command(f"HLT {self.axis}", "stop (HLT)", tolerate=(STOPPED_BY_COMMAND,))

    def reset_alarm(self) -> None:
        """Switch the servo back on after a motion error (``SVO <axis> 1``)."""
        self._command(f"SVO {self.axis} 1", "reset_alarm (SVO)")

    def state(self) -> TableState:
        servo_on = self._axis_flag("SVO?")
        on_target = self._axis_flag("ONT?")
        homed = self._axis_flag("FRF?")
        moving = self._query("#5", r"-?\d+")
        return TableState(
            in_position=on_target,
            moving=int(moving[0]) != 0,
            homed=homed,
            fault=None if servo_on else "servo off (motion error or switched off)",
            position=self.position(),
        )

    def raw_query(self, line: str) -> list[str]:
        """A GCS query as it is (for diagnostics and the benchmark)."""
        return self._query(line)

    def describe(self) -> dict[str, Any]:
        return {"port": self.port, "axis": self.axis, "identity": self.identity}
