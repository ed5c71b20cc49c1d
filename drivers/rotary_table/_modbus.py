"""``ModbusTable``: a rotary-table servo drive over Modbus TCP or RTU (pymodbus 3.16 sync clients).

Device units (counts, velocity units, opcodes) appear only at the registers, taken from the
``RegisterMap`` in the settings; the public API is in radians and rad/s.

Opening
-------
``open()`` connects, reads the status register (which proves the drive answers with this unit id and
map) and, unless ``reference_on_open`` is off, makes the table usable as a real set-up must: the
servo on (the drive powers on disabled) and the reference move if the table is unreferenced, each
within its own timeout. A drive alarm present at open is a ``TableFault``: clearing it is the
operator's decision, not the driver's.

Error handling
--------------
- A Modbus exception response (pymodbus 3.16 *returns* an ``ExceptionResponse``, function code | 0x80)
  becomes ``CommandRefused`` for code 3 (illegal data value: a target beyond the soft limits, a speed
  out of range; nothing moved), ``TableFault`` for code 4 (device failure: the drive cannot act now,
  e.g. alarm present, servo off, unreferenced; the message says which), a retry then
  ``DeviceTimeout`` for 5/6 (acknowledge/busy) and 10/11 (gateway, or no device with this unit id
  behind a TCP address), else ``ProtocolError``; every message names the register and the code.
- No answer (``ModbusIOException``) becomes ``DeviceTimeout``; if bytes did arrive but formed no valid
  frame (garbage, truncation, bad CRC) it becomes ``ProtocolError``. Both are retried ``retries``
  times, after a guard wait and a flush of stale input, so a late answer is never taken for a new one.
- Relative moves are sent as absolute targets (last target + delta), so a retried write can never
  move the table twice.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import Any

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ExceptionResponse

from drivers._errors import DeviceConnectionError, DeviceError, DeviceTimeout, MotionRefused, ProtocolError
from drivers.rotary_table._interface import CommandRefused, TableFault, TableState
from drivers.rotary_table._settings import ModbusRtuSettings, ModbusTcpSettings

# pymodbus logs each late or missing reply as a warning of its own; this driver turns the same
# events into retries or typed errors, so without an application handler they would only reach
# stderr through logging's last-resort handler. An application that configures logging still
# sees them.
logging.getLogger("pymodbus").addHandler(logging.NullHandler())

EXCEPTION_NAMES = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value: the drive refused the value",
    4: "device failure: the drive cannot act now",
    5: "acknowledge (busy, try later)",
    6: "device busy",
    7: "negative acknowledge",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target failed to respond: no device with this unit id there?",
}
_RETRYABLE_CODES = {5, 6, 10, 11}


class ModbusTable:
    """A rotary table behind a Modbus servo drive, over TCP or RTU (the settings' adapter decides).

    Parameters
    ----------
    settings : ModbusTcpSettings or ModbusRtuSettings
        Where the drive is, its unit id, register map, answer timeout, retries and poll interval.
    name : str
        Device name for errors.
    """

    def __init__(self, settings: ModbusTcpSettings | ModbusRtuSettings, *, name: str = "rotary_table") -> None:
        self.name = name
        self.settings = settings
        self.unit = settings.unit
        self.map = settings.register_map
        self.timeout = settings.timeout
        self.retries = settings.retries
        self.poll_interval = settings.poll_interval
        if isinstance(settings, ModbusTcpSettings):
            self.endpoint = f"modbus tcp {settings.host}:{settings.port}"
        else:
            self.endpoint = f"modbus rtu {settings.port}"
        self._client: Any = None  # a pymodbus client (untyped to mypy, see pyproject.toml)
        self._rx_bytes = 0
        self._target: int | None = None  # last commanded position (counts)

    def _make_client(self) -> Any:
        """A fresh pymodbus sync client (on open and after a lost connection); pymodbus does not
        retry on its own (``retries=0``): this driver's retries are the bounded ones."""
        settings = self.settings
        if isinstance(settings, ModbusTcpSettings):
            return ModbusTcpClient(settings.host, port=settings.port, timeout=settings.timeout, retries=0,
                                   reconnect_delay=0, trace_packet=self._trace)
        return ModbusSerialClient(settings.port, baudrate=settings.baudrate, timeout=settings.timeout, retries=0,
                                  reconnect_delay=0, trace_packet=self._trace)

    # ----------------------------------------------------------------------------- connection
    def _trace(self, sending: bool, data: bytes) -> bytes:
        if not sending:
            self._rx_bytes = max(self._rx_bytes, len(data))
        return data

    def open(self) -> None:
        """Connect, check the drive answers, then (``reference_on_open``) servo on and reference move.

        Raises
        ------
        DeviceConnectionError, DeviceTimeout, ProtocolError
            The drive cannot be reached or does not answer with this unit id and register map.
        TableFault
            An alarm is present, or the drive refused the servo-on or the reference move.
        DeviceTimeout
            The servo did not come on within ``servo_timeout``, or the reference move did not end
            within ``reference_timeout`` (the operation names which).
        """
        self.close()
        client = self._make_client()
        try:
            ok = client.connect()
        except Exception as exc:  # pyserial / socket errors at open
            client.close()
            raise DeviceConnectionError(self.name, f"open ({self.endpoint})", str(exc)) from None
        if not ok:
            client.close()
            raise DeviceConnectionError(self.name, f"open ({self.endpoint})", "the drive cannot be reached")
        self._client = client
        try:
            status = self._status()  # proves the drive answers with this unit id and map
            if self.settings.reference_on_open:
                self._make_ready(status)
        except DeviceError:
            self.close()
            raise

    def _make_ready(self, status: int) -> None:
        """Servo on, then the reference move if unreferenced, each bounded by its timeout."""
        bits, settings = self.map.status_bits, self.settings
        if status >> bits.alarm & 1 or status >> bits.drive_fault & 1:
            alarm = self._read(self.map.alarm, 1)[0]
            raise TableFault(self.name, "open", f"drive alarm 0x{alarm:04x} ({self.map.alarm_bits.describe(alarm)}) "
                             "present: clear its cause, then reset the alarm")
        if not status >> bits.enabled & 1:
            self._command(self.map.opcodes.enable, "open: servo on")
            self._wait(lambda s: bool(s >> bits.enabled & 1), settings.servo_timeout, "open: servo on",
                       "the servo is not on")
        if not status >> bits.homed & 1:
            self.home(settings.reference_timeout, operation="open: reference move")

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None

    def __enter__(self) -> ModbusTable:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _flush(self) -> None:
        """Throw away stale input (a late answer to an earlier request)."""
        socket: Any = getattr(self._client, "socket", None)  # a socket (TCP) or a serial.Serial (RTU)
        try:
            if hasattr(socket, "reset_input_buffer"):
                socket.reset_input_buffer()
            elif socket is not None:
                socket.setblocking(False)
                try:
                    while socket.recv(4096):
                        pass
                except (BlockingIOError, InterruptedError):
                    pass
                finally:
                    socket.setblocking(True)
                    socket.settimeout(self.timeout)
        except OSError:
            pass

    # ----------------------------------------------------------------------------- transactions
    def _transact(self, operation: str, address: int, call: Callable[[Any], Any]) -> Any:
        """Run ``call(client)`` with flush, bounded retries and typed errors."""
        register = self.map.name_of(address)
        last: DeviceError | None = None
        for attempt in range(self.retries + 1):
            if self._client is None:
                try:
                    self._reconnect()
                except DeviceConnectionError as exc:
                    last = exc
                    time.sleep(min(0.1, self.timeout))
                    continue
            self._flush()
            self._rx_bytes = 0
            try:
                response = call(self._client)
            except ConnectionException as exc:
                last = DeviceConnectionError(self.name, f"{operation} {register}", f"connection lost: {exc}")
                self.close()
                continue
            except ModbusIOException as exc:
                if self._rx_bytes:
                    last = ProtocolError(self.name, f"{operation} {register}",
                                         f"garbled or truncated answer ({self._rx_bytes} bytes, no valid frame): {exc}")
                else:
                    last = DeviceTimeout(self.name, f"{operation} {register}",
                                         f"no answer within {self.timeout} s (attempt {attempt + 1})")
                time.sleep(self.timeout)  # guard: let a late answer arrive, then it is flushed
                continue
            except ModbusException as exc:
                last = ProtocolError(self.name, f"{operation} {register}", str(exc))
                continue
            except OSError as exc:
                last = DeviceConnectionError(self.name, f"{operation} {register}", str(exc))
                self.close()
                continue
            if isinstance(response, ExceptionResponse) or response.isError():
                code = int(getattr(response, "exception_code", 0))
                text = f"Modbus exception code {code} ({EXCEPTION_NAMES.get(code, 'unknown')})"
                if code in _RETRYABLE_CODES:
                    last = DeviceTimeout(self.name, f"{operation} {register}", text)
                    time.sleep(self.poll_interval)
                    continue
                if code == 3:
                    raise CommandRefused(self.name, f"{operation} {register}", text)
                if code == 4:
                    raise TableFault(self.name, f"{operation} {register}", text + self._state_text())
                raise ProtocolError(self.name, f"{operation} {register}", text)
            return response
        assert last is not None
        raise last

    def _reconnect(self) -> None:
        """Reconnect after a lost connection (no status read)."""
        client = self._make_client()
        if not client.connect():
            client.close()
            raise DeviceConnectionError(self.name, f"reconnect ({self.endpoint})", "the drive cannot be reached")
        self._client = client

    def _state_text(self) -> str:
        """Why the drive cannot act, in words, best effort (used inside an error path): its alarm, or
        servo off, or unreferenced."""
        try:
            alarm = self._client.read_holding_registers(self.map.alarm, count=1, device_id=self.unit)
            if not alarm.isError() and alarm.registers[0]:
                return f"; drive alarm: {self.map.alarm_bits.describe(alarm.registers[0])}"
            status = self._client.read_holding_registers(self.map.status, count=1, device_id=self.unit)
            if not status.isError():
                bits, word = self.map.status_bits, status.registers[0]
                if not word >> bits.enabled & 1:
                    return "; the servo is off"
                if not word >> bits.homed & 1:
                    return "; the table is not referenced (home it)"
        except Exception:
            pass
        return ""

    def _read(self, address: int, count: int) -> list[int]:
        response = self._transact("read", address, lambda c: c.read_holding_registers(
            address, count=count, device_id=self.unit))
        registers = list(response.registers)
        if len(registers) < count:
            raise ProtocolError(self.name, f"read {self.map.name_of(address)}",
                                f"asked for {count} registers, got {len(registers)}")
        return registers[:count]

    def _write(self, address: int, values: list[int], operation: str) -> None:
        what = f"{operation}: write"
        if len(values) == 1:
            self._transact(what, address, lambda c: c.write_register(address, values[0], device_id=self.unit))
        else:
            self._transact(what, address, lambda c: c.write_registers(address, values, device_id=self.unit))

    # ----------------------------------------------------------------------------- table API
    def _check_no_alarm(self, operation: str) -> None:
        alarm = self._read(self.map.alarm, 1)[0]
        if alarm:
            raise TableFault(self.name, operation, f"drive alarm 0x{alarm:04x}: {self.map.alarm_bits.describe(alarm)}")

    def _set_speed(self, speed: float | None, operation: str) -> None:
        if speed is None:
            return
        units = self.map.rad_s_to_velocity(speed)
        if not math.isfinite(speed) or speed <= 0 or units <= 0 or units > 0xFFFF:
            raise MotionRefused(self.name, operation, f"speed {speed!r} rad/s is not a usable positive speed")
        self._write(self.map.velocity, [units], operation)

    def _command(self, opcode: int, operation: str) -> None:
        self._write(self.map.control, [opcode], operation)

    def move_absolute(self, angle: float, speed: float | None = None) -> None:
        operation = f"move_absolute({angle!r})"
        if not math.isfinite(angle):
            raise MotionRefused(self.name, operation, "target angle is not a finite number")
        counts = self.map.rad_to_counts(angle)
        if not -(2 ** 31) <= counts < 2 ** 31:
            raise MotionRefused(self.name, operation, "target outside the drive's 32-bit position range")
        self._check_no_alarm(operation)
        self._set_speed(speed, operation)
        self._write(self.map.position_command, self.map.split32(counts), operation)
        self._command(self.map.opcodes.move_absolute, operation)
        self._target = counts

    def move_relative(self, delta: float, speed: float | None = None) -> None:
        if not math.isfinite(delta):
            raise MotionRefused(self.name, f"move_relative({delta!r})", "distance is not a finite number")
        base = self._target if self._target is not None else self._encoder_counts()
        self.move_absolute(self.map.counts_to_rad(base) + delta, speed)

    def _encoder_counts(self) -> int:
        return self.map.join32(self._read(self.map.encoder_position, 2))

    def _status(self) -> int:
        return self._read(self.map.status, 1)[0]

    def _wait(self, done: Callable[[int], bool], timeout: float, operation: str,
              not_yet: str = "not in position") -> None:
        bits = self.map.status_bits
        deadline = time.monotonic() + timeout
        while True:
            status = self._status()
            if status >> bits.alarm & 1 or status >> bits.drive_fault & 1:
                alarm = self._read(self.map.alarm, 1)[0]
                raise TableFault(
                    self.name, operation, f"drive alarm 0x{alarm:04x}: {self.map.alarm_bits.describe(alarm)}"
                )
            if done(status):
                return
            if time.monotonic() > deadline:
                raise DeviceTimeout(self.name, operation, f"{not_yet} after {timeout} s (status 0x{status:04x})")
            time.sleep(self.poll_interval)

    def wait_in_position(self, timeout: float = 30.0) -> float:
        bits = self.map.status_bits
        self._wait(lambda s: bool(s >> bits.in_position & 1) and not s >> bits.moving & 1, timeout, "wait_in_position")
        return self.position()

    def home(self, timeout: float = 30.0, *, operation: str = "home") -> None:
        """Seek the reference mark (the true zero) and wait until the drive reports it homed."""
        bits = self.map.status_bits
        self._check_no_alarm(operation)
        self._command(self.map.opcodes.home, operation)
        self._wait(lambda s: bool(s >> bits.homed & 1) and bool(s >> bits.in_position & 1)
                   and not s >> bits.homing & 1, timeout, operation, "not referenced")
        self._target = 0

    def position(self) -> float:
        return self.map.counts_to_rad(self._encoder_counts())

    def stop(self) -> None:
        self._command(self.map.opcodes.stop, "stop")
        self._target = None

    def reset_alarm(self) -> None:
        """Clear the drive's alarm (the cause must be gone)."""
        self._command(self.map.opcodes.alarm_reset, "reset_alarm")

    def state(self) -> TableState:
        m, bits = self.map, self.map.status_bits
        alarm = self._read(m.alarm, 1)[0]
        status = self._status()
        position = self.position()
        return TableState(
            in_position=bool(status >> bits.in_position & 1),
            moving=bool(status >> bits.moving & 1),
            homed=bool(status >> bits.homed & 1),
            fault=m.alarm_bits.describe(alarm) if alarm else None,
            position=position,
        )
