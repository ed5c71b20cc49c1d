"""The wire conventions, decoded in this file from the documentation, against the twins' ground truth.

The twins and the drivers each encode their protocol with their own code; this file is a third,
written from ``docs/rotary_table.md`` and ``docs/interferometer.md`` alone, so a convention slip
(word order, scale, byte order, sign, CRC) on either side fails here instead of cancelling out:

- raw Modbus registers read with a plain pymodbus client, decoded here, against the world's true
  table angle; raw register writes in the documented encoding move the table where they say; the
  documented power-on state, exception codes and device-id rules;
- raw GCS lines over TCP (a socket) and over the serial face (pyserial): the documented power-on
  refusal (error 5), servo on, reference move, soft limits (error 7) and answer format;
- raw CAN frames captured with python-can, decoded here (int40 little-endian, counter, status
  bits, CRC-8/SAE-J1850), against the interferometer head's true displacement; raw socketcand text
  read from a plain socket (3-hex-digit ids, ``sec.usec`` receive timestamps in bus order); the
  environmental unit's frames (uint16 fields, offsets, fault bits, cycle counter) against the air
  of the ambient model, computed here from the seed and the frame's time;
- the driver against the same truth, and the same check run on a driver with its word order
  swapped, its byte order swapped or its scale off (monkeypatched here only) must fail.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import socket
import struct
import time
from collections.abc import Callable, Iterator

import can
import pytest
import serial
from pymodbus.client import ModbusTcpClient

from drivers import DeviceError
from drivers.interferometer import FrameLayout
from drivers.interferometer import create as create_interferometer
from drivers.rotary_table import RegisterMap
from drivers.rotary_table import create as create_table
from sim_devices import World, WorldConfig
from sim_devices.ambient import AmbientModel
from sim_devices.interferometer import InterferometerTwin, move_opr
from sim_devices.rotary_table import RotaryTableTwin

pytestmark = pytest.mark.timeout(120)

TURN = 2.0 * math.pi
FAST_TABLE = {"max_speed": 3.0, "peak_torque": 1.0, "home_speed": 3.0, "seed": 7}


def _wait_until(predicate: Callable[[], bool], what: str, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


# ===================================================================================== Modbus
# docs/rotary_table.md: holding registers, 0-based. Default map: 0 alarm, 1 status, 2-3 encoder
# position (s32, counts), 4-5 position command (s32), 6 velocity (u16, 1/240 rev/s), 7 acceleration
# (u16, 1/6 rev/s²), 8 actual velocity (s16), 124 control (opcode). Word order "big": high word first.
# 2**24 counts per revolution. Status bits: 0 enabled, 3 in position, 4 moving, 13 homed.
# Opcodes: 0x67 move absolute, 0x6E home.
DEFAULT_MAP = {"alarm": 0, "status": 1, "encoder": 2, "command": 4, "velocity": 6, "acceleration": 7,
               "actual_velocity": 8, "control": 124, "little": False, "counts_per_rev": 2**24}
# The driver test's non-default map: moved addresses, low word first, 2**23 counts per revolution.
OTHER_MAP = {"alarm": 40, "status": 41, "encoder": 10, "command": 20, "velocity": 30, "acceleration": 31,
             "actual_velocity": 32, "control": 50, "little": True, "counts_per_rev": 2**23}
OTHER_MAP_CONFIG = {"alarm": 40, "status": 41, "encoder_position": 10, "position_command": 20, "velocity": 30,
                    "acceleration": 31, "actual_velocity": 32, "control": 50, "word_order": "little",
                    "counts_per_rev": 8_388_608}
ENABLED, IN_POSITION, MOVING, HOMED = 0, 3, 4, 13
MOVE_ABSOLUTE, MOVE_RELATIVE, HOME, ENABLE = 0x67, 0x66, 0x6E, 0x9F
# Exception codes: 2 illegal address (unmapped or read-only), 3 illegal value (a word of 0 or above
# the maximum, an unknown opcode, a target beyond the ±36000° soft limits), 4 cannot act now (servo
# off, unreferenced, alarm). Other unit ids: exception 11 over TCP (0 and 255 name the drive itself).
ILLEGAL_ADDRESS, ILLEGAL_VALUE, DEVICE_FAILURE, GATEWAY_NO_RESPONSE = 2, 3, 4, 11
TRAVEL_DEG = 36_000.0


def _s32(first: int, second: int, low_word_first: bool) -> int:
    """Two registers (in address order) as the documented signed 32-bit value."""
    high, low = (second, first) if low_word_first else (first, second)
    value = high << 16 | low
    return value - (1 << 32) if value >= 1 << 31 else value


def _words(value: int, low_word_first: bool) -> list[int]:
    high, low = (value >> 16) & 0xFFFF, value & 0xFFFF
    return [low, high] if low_word_first else [high, low]


class RawDrive:
    """A plain pymodbus client that knows the register map only from the documentation."""

    def __init__(self, port: int, layout: dict) -> None:
        self.layout = layout
        self.client = ModbusTcpClient("127.0.0.1", port=port, timeout=2.0, retries=1)
        assert self.client.connect()

    def read(self, name: str, count: int = 1) -> list[int]:
        reply = self.client.read_holding_registers(self.layout[name], count=count, device_id=1)
        assert not reply.isError(), reply
        return list(reply.registers)

    def status_bit(self, bit: int) -> bool:
        return bool(self.read("status")[0] >> bit & 1)

    def counts(self) -> int:
        return _s32(*self.read("encoder", 2), self.layout["little"])

    def angle(self) -> float:
        return self.counts() * TURN / self.layout["counts_per_rev"]

    def command(self, opcode: int, target_counts: int | None = None) -> None:
        reply = self.try_command(opcode, target_counts)
        assert not reply.isError(), reply

    def try_command(self, opcode: int, target_counts: int | None = None):
        """Write the target (if any) and the opcode; the opcode write's reply."""
        if target_counts is not None:
            reply = self.client.write_registers(self.layout["command"], _words(target_counts, self.layout["little"]),
                                                device_id=1)
            assert not reply.isError(), reply
        return self.client.write_register(self.layout["control"], opcode, device_id=1)

    def ready(self) -> None:
        """What a set-up does after power-on: enable, then home."""
        self.command(ENABLE)
        _wait_until(lambda: self.status_bit(ENABLED), "enabled")
        self.command(HOME)
        _wait_until(lambda: self.status_bit(HOMED), "homed")
        self.wait_in_position()

    def wait_in_position(self) -> None:
        _wait_until(lambda: self.status_bit(IN_POSITION) and not self.status_bit(MOVING), "in position")

    def close(self) -> None:
        self.client.close()


def _table_twin(register_map: dict | None = None) -> Iterator[tuple[World, RotaryTableTwin, int]]:
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    world = World(WorldConfig(seed=7))
    world.mount_on_table("z")
    config: dict = {"transports": ["modbus_tcp"], "table": FAST_TABLE}
    if register_map is not None:
        config["register_map"] = register_map
    twin = RotaryTableTwin(world, config)
    port = twin.start()["modbus_tcp_port"]
    twin.sync()
    try:
        yield world, twin, port
    finally:
        twin.stop()
        world.truth.close()


@pytest.fixture
def table_twin() -> Iterator[tuple[World, RotaryTableTwin, int]]:
    yield from _table_twin()


@pytest.fixture
def homed_drive(table_twin) -> Iterator[tuple[World, RotaryTableTwin, RawDrive]]:
    world, twin, port = table_twin
    drive = RawDrive(port, DEFAULT_MAP)
    drive.ready()
    yield world, twin, drive
    drive.close()


def _bound(twin: RotaryTableTwin, counts_per_rev: int) -> float:
    """|reported − true| the table may show once homed, plus half a count of the register scale."""
    return twin.table_config.reported_error_bound() + math.pi / counts_per_rev


@pytest.mark.parametrize("target", [-1.234, 2.5])
def test_modbus_registers_decode_to_the_true_table_angle(homed_drive, target):
    world, twin, drive = homed_drive
    target_counts = round(target / TURN * DEFAULT_MAP["counts_per_rev"])
    assert target_counts >> 16 not in (0, -1)  # both words carry information at these angles
    drive.command(MOVE_ABSOLUTE, target_counts)  # written in the documented encoding
    drive.wait_in_position()
    _wait_until(lambda: world.state().settled and twin.physics.settled(), "the world to see the table settle")
    true_angle = world.table_angle()
    bound = _bound(twin, DEFAULT_MAP["counts_per_rev"])
    assert abs(true_angle - target) <= bound  # the twin executed the documented command where it says
    assert abs(drive.angle() - true_angle) <= bound  # and reports it in the documented encoding
    assert drive.read("command", 2) == _words(target_counts, low_word_first=False)
    status = drive.read("status")[0]
    assert status >> ENABLED & 1 and status >> IN_POSITION & 1 and not status >> MOVING & 1 and status >> HOMED & 1
    assert drive.read("alarm") == [0]
    assert drive.read("actual_velocity") == [0]  # at rest
    # Velocity and acceleration settings: 1/240 rev/s and 1/6 rev/s² per unit.
    assert drive.read("velocity")[0] == round(twin.physics.speed / TURN * 240)
    assert drive.read("acceleration")[0] == round(twin.physics.acceleration / TURN * 6)
    reply = drive.client.write_register(DEFAULT_MAP["velocity"], 60, device_id=1)  # 60/240 rev/s
    assert not reply.isError()
    assert twin.physics.speed == pytest.approx(60 / 240 * TURN)


def test_modbus_actual_velocity_is_signed_while_moving(homed_drive):
    world, twin, drive = homed_drive
    drive.command(MOVE_ABSOLUTE, -round(3.0 / TURN * DEFAULT_MAP["counts_per_rev"]))  # a long move downwards
    seen: list[int] = []

    def moving_down() -> bool:
        word = drive.read("actual_velocity")[0]
        seen.append(word - 0x10000 if word & 0x8000 else word)
        return seen[-1] < 0

    _wait_until(moving_down, "a negative actual velocity")
    assert -round(twin.table_config.max_speed / TURN * 240) - 1 <= seen[-1] < 0
    drive.wait_in_position()


@pytest.fixture
def other_table_twin() -> Iterator[tuple[World, RotaryTableTwin, int]]:
    yield from _table_twin(OTHER_MAP_CONFIG)


def test_a_non_default_register_map_is_served_as_configured(other_table_twin):
    world, twin, port = other_table_twin
    drive = RawDrive(port, OTHER_MAP)
    try:
        drive.ready()
        target_counts = round(-2.5 / TURN * OTHER_MAP["counts_per_rev"])
        drive.command(MOVE_ABSOLUTE, target_counts)
        drive.wait_in_position()
        _wait_until(lambda: twin.physics.settled() and world.state().settled, "settled")
        bound = _bound(twin, OTHER_MAP["counts_per_rev"])
        assert abs(world.table_angle() + 2.5) <= bound
        assert abs(drive.angle() - world.table_angle()) <= bound
        assert drive.read("command", 2) == _words(target_counts, low_word_first=True)
        assert drive.read("command", 2)[1] == (target_counts >> 16) & 0xFFFF  # the high word second
    finally:
        drive.close()


def test_modbus_power_on_state_and_exception_codes(table_twin):
    world, twin, port = table_twin
    drive = RawDrive(port, DEFAULT_MAP)
    try:
        status = drive.read("status")[0]
        assert not status >> ENABLED & 1 and not status >> HOMED & 1  # powered on: disabled, unreferenced
        refused = drive.try_command(HOME)
        assert refused.isError() and refused.exception_code == DEVICE_FAILURE  # cannot act now: servo off
        drive.command(ENABLE)
        refused = drive.try_command(MOVE_ABSOLUTE, 1000)
        assert refused.isError() and refused.exception_code == DEVICE_FAILURE  # not referenced yet
        drive.ready()
        beyond = round((TRAVEL_DEG + 1.0) / 360.0 * DEFAULT_MAP["counts_per_rev"])
        for opcode, counts in ((MOVE_ABSOLUTE, beyond), (MOVE_ABSOLUTE, -beyond), (MOVE_RELATIVE, beyond)):
            refused = drive.try_command(opcode, counts)
            assert refused.isError() and refused.exception_code == ILLEGAL_VALUE, (opcode, counts)
            assert not drive.status_bit(MOVING) and drive.read("alarm") == [0]  # no motion, no alarm
        refused = drive.try_command(0x42)  # no such opcode
        assert refused.isError() and refused.exception_code == ILLEGAL_VALUE
        for register in ("velocity", "acceleration"):
            value = drive.read(register)[0]
            for word in (0, value + 1_000):
                reply = drive.client.write_register(DEFAULT_MAP[register], word, device_id=1)
                assert reply.isError() and reply.exception_code == ILLEGAL_VALUE, (register, word)
            assert not drive.client.write_register(DEFAULT_MAP[register], value, device_id=1).isError()
            assert drive.read(register) == [value]  # what is read back can be written back
        reply = drive.client.write_register(DEFAULT_MAP["status"], 1, device_id=1)  # read-only
        assert reply.isError() and reply.exception_code == ILLEGAL_ADDRESS
        reply = drive.client.read_holding_registers(DEFAULT_MAP["control"] + 1, count=1, device_id=1)  # unmapped
        assert reply.isError() and reply.exception_code == ILLEGAL_ADDRESS
        for unit in (0, 255):
            reply = drive.client.read_holding_registers(DEFAULT_MAP["status"], count=1, device_id=unit)
            assert not reply.isError() and reply.registers == drive.read("status")
        reply = drive.client.read_holding_registers(DEFAULT_MAP["status"], count=1, device_id=7)
        assert reply.isError() and reply.exception_code == GATEWAY_NO_RESPONSE
    finally:
        drive.close()


# ----------------------------------------------------------------------- GCS lines
# docs/rotary_table.md: GCS 2.0, axis "1", degrees; set commands silent, errors latched and read with
# ERR?; "<axis>=<value>" answers. Power-on: servo off, unreferenced: MOV latches 5 until "SVO 1 1"
# and "FRF 1". Soft limits ±36000° (TMN?/TMX?): a MOV beyond latches 7. The TCP face is the same.
class RawGcs:
    """GCS lines over a plain socket or a pyserial port, knowing only the documented syntax."""

    def __init__(self, port) -> None:
        self.port = port

    def ask(self, line: str) -> list[str]:
        self.port.write(line.encode("ascii") + b"\n")
        lines = []
        while True:
            raw = self.port.read_until(b"\n")
            assert raw.endswith(b"\n"), f"no answer to {line!r}: {raw!r}"
            if raw.endswith(b" \n"):
                lines.append(raw[:-2].decode("ascii"))
                continue
            lines.append(raw[:-1].decode("ascii"))
            return lines

    def tell(self, line: str) -> int:
        """A set command, then its latched error code."""
        self.port.write(line.encode("ascii") + b"\n")
        return int(self.ask("ERR?")[0])

    def value(self, query: str) -> float:
        (answer,) = self.ask(f"{query} 1")
        axis, value = answer.split("=")
        assert axis == "1"
        return float(value)


class _SocketPort:
    """``write``/``read_until`` on a TCP socket, as pyserial offers them on a serial port."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=5.0)
        self.buffer = b""

    def write(self, data: bytes) -> None:
        self.sock.sendall(data)

    def read_until(self, end: bytes) -> bytes:
        while end not in self.buffer:
            chunk = self.sock.recv(4096)
            if not chunk:
                break
            self.buffer += chunk
        index = self.buffer.find(end)
        line, self.buffer = (self.buffer, b"") if index < 0 else (self.buffer[:index + 1], self.buffer[index + 1:])
        return line

    def close(self) -> None:
        self.sock.close()


@pytest.fixture(params=["gcs", "gcs_tcp"])
def gcs_line(request) -> Iterator[tuple[World, RotaryTableTwin, RawGcs]]:
    world = World(WorldConfig(seed=7))
    world.mount_on_table("z")
    twin = RotaryTableTwin(world, {"transports": [request.param], "table": FAST_TABLE})
    endpoints = twin.start()
    twin.sync()
    port = (_SocketPort(endpoints["gcs_tcp_port"]) if request.param == "gcs_tcp"
            else serial.Serial(endpoints["gcs_port"], timeout=5.0))
    try:
        yield world, twin, RawGcs(port)
    finally:
        port.close()
        twin.stop()
        world.truth.close()


def test_gcs_lines_power_on_reference_limits_and_truth(gcs_line):
    world, twin, gcs = gcs_line
    assert gcs.ask("CSV?") == ["2.0"]
    assert gcs.value("SVO?") == 0 and gcs.value("FRF?") == 0  # powered on: servo off, unreferenced
    assert gcs.tell("MOV 1 10") == 5
    assert gcs.tell("FRF 1") == 5  # the reference move needs the servo
    assert gcs.tell("SVO 1 1") == 0 and gcs.value("SVO?") == 1
    assert gcs.tell("MOV 1 10") == 5  # still unreferenced
    assert gcs.tell("FRF 1") == 0
    _wait_until(lambda: gcs.value("FRF?") == 1 and gcs.value("ONT?") == 1, "referenced")
    assert gcs.value("TMN?") == -TRAVEL_DEG and gcs.value("TMX?") == TRAVEL_DEG
    assert gcs.tell(f"MOV 1 {TRAVEL_DEG + 1}") == 7 and gcs.tell(f"MOV 1 {-TRAVEL_DEG - 1}") == 7
    assert gcs.value("ONT?") == 1 and abs(gcs.value("POS?")) < 1e-3  # nothing moved
    assert gcs.tell("MOV 1 -20.5") == 0
    _wait_until(lambda: gcs.value("ONT?") == 1, "on target")
    _wait_until(lambda: world.state().settled and twin.physics.settled(), "settled")
    bound = math.degrees(_bound(twin, 2**24))
    assert abs(math.degrees(world.table_angle()) + 20.5) <= bound
    assert abs(gcs.value("POS?") - math.degrees(world.table_angle())) <= bound
    lines = gcs.ask("HLP?")  # multi-line: every line but the last ends with " \n" (checked in ask)
    assert len(lines) > 2 and lines[0].startswith("The following")


# ----------------------------------------------------------------------- the check has teeth
def _table_error(table, world: World) -> float:
    return abs(table.position() - world.table_angle())


def _join32_other_word_order(self, words):
    first, second = words[0], words[1]
    high, low = (second, first) if self.word_order == "big" else (first, second)
    raw = (high << 16) | low
    return raw - (1 << 32) if raw & 0x80000000 else raw


def test_the_driver_vs_truth_check_fails_on_a_wrong_word_order_or_scale(homed_drive, table_twin, monkeypatch):
    world, twin, drive = homed_drive
    drive.command(MOVE_ABSOLUTE, round(-1.234 / TURN * DEFAULT_MAP["counts_per_rev"]))
    drive.wait_in_position()
    _wait_until(lambda: world.state().settled and twin.physics.settled(), "settled")
    bound = _bound(twin, DEFAULT_MAP["counts_per_rev"])
    port = table_twin[2]
    with create_table({"adapter": "modbus_tcp", "host": "127.0.0.1", "port": port, "unit": 1}, name="table") as table:
        assert _table_error(table, world) <= bound  # the driver as it is agrees with the truth
        with monkeypatch.context() as patch:
            patch.setattr(RegisterMap, "join32", _join32_other_word_order)
            assert _table_error(table, world) > bound, "a swapped word order went unnoticed"
        with monkeypatch.context() as patch:
            patch.setattr(RegisterMap, "counts_to_rad", lambda self, counts: counts * TURN / (self.counts_per_rev / 2))
            assert _table_error(table, world) > bound, "a scale off by 2 went unnoticed"
        assert _table_error(table, world) <= bound  # and nothing of the above leaked


# ======================================================================================== CAN
# docs/interferometer.md: standard 11-bit ids, 8 data bytes. Displacement 0x181: bytes 0..4 int40
# little-endian in 1e-10 m, 5 counter (+1 per sample, mod 256), 6 status (bit0 beam OK, bit1 signal
# low, bit2 datum set, bit3 overrange, bits 4..7 signal /15), 7 CRC-8/SAE-J1850 (poly 0x1D, init
# 0xFF, xor-out 0xFF) over the id (2 bytes big-endian) and bytes 0..6. Status 0x281: 0 status bits,
# 1..2 uint16 LE signal 0..65535, 3 axis (0 x, 1 y, 2 z), 4 datum generation, 6 heartbeat.
# Command 0x601: 0 opcode (1 datum, 2 sync), 1 token. Reply 0x581: 0 opcode, 1 token, 2 result, 3 generation.
DISPLACEMENT_ID, STATUS_ID, COMMAND_ID, REPLY_ID = 0x181, 0x281, 0x601, 0x581
RESOLUTION = 1e-10
BEAM_OK, SIGNAL_LOW, DATUM_SET, OVERRANGE = 0x01, 0x02, 0x04, 0x08
DATUM, SYNC = 1, 2


def _crc8_sae_j1850(data: bytes) -> int:
    crc = 0xFF
    for byte in data:
        for bit in range(7, -1, -1):
            top = (crc >> 7) ^ (byte >> bit & 1)
            crc = (crc << 1) & 0xFF
            if top:
                crc ^= 0x1D
    return crc ^ 0xFF


def test_the_crc_here_is_the_catalogue_crc():
    assert _crc8_sae_j1850(b"123456789") == 0x4B  # the catalogue check value
    example = bytes.fromhex("15CD5B07002AE5EE")  # the worked example of docs/interferometer.md
    assert _crc8_sae_j1850(struct.pack(">H", DISPLACEMENT_ID) + example[:7]) == example[7]


def _sealed(can_id: int, body: bytes) -> bytes:
    return body + bytes([_crc8_sae_j1850(struct.pack(">H", can_id) + body)])


def _good_crc(message: can.Message) -> bool:
    data = bytes(message.data)
    return len(data) == 8 and _crc8_sae_j1850(struct.pack(">H", message.arbitration_id) + data[:7]) == data[7]


@pytest.fixture
def ifm_twin() -> Iterator[tuple[World, InterferometerTwin]]:
    world = World(WorldConfig(seed=13))
    twin = InterferometerTwin(world)
    twin.start()
    try:
        yield world, twin
    finally:
        twin.stop()
        world.truth.close()


@pytest.fixture
def raw_bus(ifm_twin) -> Iterator[can.BusABC]:
    _, twin = ifm_twin
    bus = can.Bus(interface="slcan", channel=twin.endpoints["slcan"]["port"], bitrate=1_000_000, sleep_after_open=0)
    try:
        yield bus
    finally:
        bus.shutdown()


def _command(bus: can.BusABC, opcode: int, token: int) -> bytes:
    """Send a command and return the data of its reply (every frame after it is newer, as documented)."""
    data = _sealed(COMMAND_ID, bytes([opcode, token, 0, 0, 0, 0, 0]))
    bus.send(can.Message(arbitration_id=COMMAND_ID, data=data, is_extended_id=False))
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:
        message = bus.recv(timeout=0.5)
        if message is not None and message.arbitration_id == REPLY_ID and message.data[1] == token:
            assert _good_crc(message)
            return bytes(message.data)
    raise AssertionError(f"no reply to command {opcode} (token {token})")


def _capture(bus: can.BusABC, seconds: float) -> list[can.Message]:
    frames, deadline = [], time.monotonic() + seconds
    while time.monotonic() < deadline:
        message = bus.recv(timeout=0.1)
        if message is not None:
            frames.append(message)
    return frames


def _displacement(data: bytes) -> float:
    return int.from_bytes(data[0:5], "little", signed=True) * RESOLUTION


@pytest.mark.parametrize("move", [0.0123456789, -0.0234567891])
def test_can_frames_decode_to_the_true_displacement(ifm_twin, raw_bus, move):
    world, twin = ifm_twin
    reply = _command(raw_bus, DATUM, token=41)
    assert reply[0] == DATUM and reply[2] == 0 and reply[3] == twin.truth()["datum_generation"] == 1
    move_opr(world, [move, 0.0, 0.0])  # the head is aimed along x at start
    assert _command(raw_bus, SYNC, token=42)[2] == 0
    frames = _capture(raw_bus, 0.35)
    truth = twin.truth()

    displacement = [f for f in frames if f.arbitration_id == DISPLACEMENT_ID]
    assert len(displacement) >= 50 and all(_good_crc(f) and not f.is_extended_id for f in displacement)
    # Sign, byte order and scale: every frame is the true displacement (scale error and the air's
    # n/n_nominal included) plus the head's noise (2 nm rms; 6 σ) and the rounding to a count.
    expected = (1.0 + truth["scale_error"]) * truth["refraction_ratio"] * truth["true_displacement"]
    assert abs(expected - move) < 1e-6  # the truth itself: the reflector moved by ``move`` along the beam
    bound = 6 * twin.config.noise_std + RESOLUTION
    assert all(abs(_displacement(bytes(f.data)) - expected) <= bound for f in displacement)
    # Counter: +1 per sample; a gap only where the twin itself says it skipped samples (a starved host).
    steps = [(b.data[5] - a.data[5]) % 256 for a, b in zip(displacement, displacement[1:])]
    stats = twin.stats()
    assert sum(step != 1 for step in steps) <= stats["late_skipped"] + stats["slcan_overflows"]
    # Status: beam OK and datum set, signal strength in the top nibble.
    nibble = round(truth["signal"] * 15)
    assert all(f.data[6] == BEAM_OK | DATUM_SET | nibble << 4 for f in displacement)

    status = [f for f in frames if f.arbitration_id == STATUS_ID]
    assert status and all(_good_crc(f) for f in status)
    for frame in status:
        assert frame.data[0] == BEAM_OK | DATUM_SET
        assert abs(int.from_bytes(frame.data[1:3], "little") - truth["signal"] * 65535) <= 1
        assert (frame.data[3], frame.data[4]) == (0, 1)  # aimed along x, one datum so far
    heartbeats = [f.data[6] for f in status]
    heartbeat_steps = [(b - a) % 256 for a, b in zip(heartbeats, heartbeats[1:])]
    assert all(step == 1 for step in heartbeat_steps) or twin.stats()["slcan_overflows"]


def test_a_command_with_a_bad_crc_is_ignored(ifm_twin, raw_bus):
    _, twin = ifm_twin
    data = bytearray(_sealed(COMMAND_ID, bytes([DATUM, 9, 0, 0, 0, 0, 0])))
    data[7] ^= 0x01
    raw_bus.send(can.Message(arbitration_id=COMMAND_ID, data=data, is_extended_id=False))
    frames = _capture(raw_bus, 0.3)
    assert not [f for f in frames if f.arbitration_id == REPLY_ID]
    assert twin.truth()["datum_generation"] == 0
    assert _command(raw_bus, DATUM, token=10)[3] == 1  # the same command with its CRC right is done


# docs/interferometer.md, environmental unit: per cycle (environment_rate, 1 Hz by default) the air
# frame 0x381 then the material frame 0x481. uint16 little-endian fields, 0xFFFF = no reading: air
# temperature in mK above 0 °C, pressure in Pa above 60 000 Pa, humidity in 0.01 % RH; material
# temperatures 1..3 in mK above 0 °C. Byte 6: bits 0..2 fault (air: temperature, pressure, humidity;
# material: 1..3), bits 4..7 the cycle counter (+1 per cycle, mod 16, the same in both frames).
ENV_AIR_ID, ENV_MATERIAL_ID = 0x381, 0x481
NO_READING = 0xFFFF
ENV_SEED = 14


def _u16(data: bytes, index: int) -> int:
    return int.from_bytes(data[2 * index:2 * index + 2], "little")


@pytest.fixture
def env_twin() -> Iterator[tuple[World, InterferometerTwin]]:
    """Two material sensors, 20 cycles a second, sensors without noise (their offsets stay: they are truth)."""
    world = World(WorldConfig(seed=ENV_SEED))
    silent = dict.fromkeys(("air_temperature_noise", "pressure_noise", "humidity_noise", "material_noise"), 0.0)
    twin = InterferometerTwin(world, {"layout": {"environment_rate": 20.0}, "ambient": {"material_sensors": 2},
                                      "environment_sensors": silent})
    twin.start()
    try:
        yield world, twin
    finally:
        twin.stop()
        world.truth.close()


@pytest.fixture
def env_bus(env_twin) -> Iterator[can.BusABC]:
    _, twin = env_twin
    bus = can.Bus(interface="slcan", channel=twin.endpoints["slcan"]["port"], bitrate=1_000_000, sleep_after_open=0)
    try:
        yield bus
    finally:
        bus.shutdown()


def test_environment_frames_decode_to_the_twins_air(env_twin, env_bus):
    _, twin = env_twin
    unit = twin.environment()
    model = AmbientModel(ENV_SEED, twin.config.ambient)  # the cell's air, from the seed alone
    offsets = unit["sensor_offsets"]
    # Until 16 environment frames have come (about 0.4 s idle); a loaded machine may take longer.
    frames: list[can.Message] = []
    deadline = time.monotonic() + 15.0
    while len(frames) < 16 and time.monotonic() < deadline:
        frames += [f for f in _capture(env_bus, 0.2) if f.arbitration_id in (ENV_AIR_ID, ENV_MATERIAL_ID)]
    assert len(frames) >= 16 and all(_good_crc(f) and not f.is_extended_id for f in frames)
    # Air first, then the material frame of the same cycle; the counter steps by one per cycle.
    start = 0 if frames[0].arbitration_id == ENV_AIR_ID else 1
    pairs = [(frames[i], frames[i + 1]) for i in range(start, len(frames) - 1, 2)]
    assert all(a.arbitration_id == ENV_AIR_ID and m.arbitration_id == ENV_MATERIAL_ID for a, m in pairs)
    assert all(a.data[6] >> 4 == m.data[6] >> 4 for a, m in pairs)
    counters = [a.data[6] >> 4 for a, _ in pairs]
    assert all((b - a) % 16 == 1 for a, b in zip(counters, counters[1:])) or twin.stats()["slcan_overflows"]
    for air_frame, material_frame in pairs:
        air, material = bytes(air_frame.data), bytes(material_frame.data)
        truth = model.at(air_frame.timestamp - unit["origin"])
        # Half a count of each field, plus the air's drift over up to 2 s between the twin's sending and
        # python-can's reading (slcan frames are stamped on reading): at most 4.6e-4 K/s, 0.02 Pa/s, 0.003 %/s.
        assert abs(_u16(air, 0) / 1000 - (truth.air_temperature_c + offsets["air_temperature"])) <= 0.0014
        assert abs(_u16(air, 1) + 60_000 - (truth.pressure_pa + offsets["pressure"])) <= 0.6
        assert abs(_u16(air, 2) / 100 - (truth.relative_humidity_percent + offsets["humidity"])) <= 0.011
        for index in range(2):
            expected = truth.material_temperatures_c[index] + offsets[f"material{index + 1}"]
            assert abs(_u16(material, index) / 1000 - expected) <= 0.0014
        assert _u16(material, 2) == NO_READING  # the third sensor is not fitted: no reading, no fault
        assert air[6] & 0x0F == 0 and material[6] & 0x0F == 0

    twin.sensor_fault("pressure")
    twin.sensor_fault("material2")
    frames = _capture(env_bus, 0.4)

    def from_first_faulty(can_id: int) -> list[bytes]:
        """The frames of ``can_id`` from the first that reports a fault on (the bus still held older ones)."""
        data = [bytes(f.data) for f in frames if f.arbitration_id == can_id]
        return data[next(i for i, d in enumerate(data) if d[6] & 0x0F):]

    air, material = from_first_faulty(ENV_AIR_ID), from_first_faulty(ENV_MATERIAL_ID)
    assert len(air) >= 2 and len(material) >= 2
    assert all(_u16(d, 1) == NO_READING and d[6] & 0x0F == 0b010 for d in air)  # pressure: bit 1
    assert all(_u16(d, 0) != NO_READING and _u16(d, 2) != NO_READING for d in air)
    assert all(_u16(d, 1) == NO_READING and d[6] & 0x0F == 0b010 for d in material)  # material 2: bit 1


# docs/interferometer.md, socketcand: "< hi >" alone, "< ok >" to open and rawmode, then
# "< frame <3 hex digits> <sec>.<usec> <hex data> >", the timestamp being the frame's receive time on
# the bus (epoch seconds), in bus order.
_FRAME = re.compile(rb"< frame ([0-9A-F]{3}) (\d+)\.(\d{6}) ([0-9A-F]*) >")


def test_socketcand_text_on_the_wire(ifm_twin):
    _, twin = ifm_twin
    endpoint = twin.endpoints["socketcand"]
    with socket.create_connection((endpoint["host"], endpoint["port"]), timeout=5.0) as sock:
        assert sock.recv(64) == b"< hi >"
        sock.sendall(f"< open {endpoint['channel']} >".encode())
        assert sock.recv(64) == b"< ok >"
        sock.sendall(b"< rawmode >")
        assert sock.recv(64) == b"< ok >"
        text, deadline = b"", time.monotonic() + 0.5
        while time.monotonic() < deadline:
            text += sock.recv(65536)
    frames = _FRAME.findall(text)
    assert len(frames) > 100 and len(frames) == text.count(b"< frame")
    stamps = [int(sec) + int(usec) / 1e6 for _, sec, usec, _ in frames]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert abs(stamps[-1] - time.time()) < 1.0
    displacement = [(int(i, 16), bytes.fromhex(d.decode())) for i, _, _, d in frames if int(i, 16) == DISPLACEMENT_ID]
    assert displacement and all(_good_crc(can.Message(arbitration_id=i, data=d)) for i, d in displacement)


# ----------------------------------------------------------------------- the check has teeth
def _has_sample(ifm) -> bool:
    try:
        ifm.latest(max_age=2.0)
    except DeviceError:
        return False
    return True


def _interferometer_error(ifm, world: World, twin: InterferometerTwin, move: float = 0.05) -> tuple[float, float]:
    """``(|driver − truth|, bound)`` for a move of ``move`` along the beam after a datum."""
    ifm.zero()
    start = world.opr_in_m()[:3, 3].copy()
    move_opr(world, [move, 0.0, 0.0])
    try:
        measured = ifm.average(0.1)
        moved = world.opr_in_m()[:3, 3] - start
        truth = twin.truth()
        expected = (1.0 + truth["scale_error"]) * truth["refraction_ratio"] * sum(
            u * d for u, d in zip(truth["beam_direction"], moved))
        samples = round(0.1 * twin.config.layout.sample_rate)
        bound = 6 * twin.config.noise_std / math.sqrt(samples) + 2 * RESOLUTION
        return abs(measured - expected), bound
    finally:
        move_opr(world, [-move, 0.0, 0.0])


def test_the_driver_vs_truth_check_fails_on_a_wrong_byte_order_or_scale(ifm_twin, monkeypatch):
    from drivers.interferometer import _can  # the driver's module, patched here only

    world, twin = ifm_twin
    with create_interferometer(twin.station_entry("socketcand"), name="interferometer") as ifm:
        _wait_until(lambda: _has_sample(ifm), "a first sample")
        error, bound = _interferometer_error(ifm, world, twin)
        assert error <= bound  # the driver as it is agrees with the truth

        original = _can.decode_displacement

        def big_endian(device, can_id, data):
            frame = original(device, can_id, data)
            return dataclasses.replace(frame, counts=int.from_bytes(bytes(data[0:5]), "big", signed=True))

        with monkeypatch.context() as patch:
            patch.setattr(_can, "decode_displacement", big_endian)
            error, bound = _interferometer_error(ifm, world, twin)
            assert error > bound, "a swapped byte order went unnoticed"
        with monkeypatch.context() as patch:
            patch.setattr(ifm, "layout", FrameLayout(resolution=10 * RESOLUTION))
            error, bound = _interferometer_error(ifm, world, twin)
            assert error > bound, "a scale off by 10 went unnoticed"
        error, bound = _interferometer_error(ifm, world, twin)
        assert error <= bound


def _environment_error(ifm, twin: InterferometerTwin) -> float:
    """|driver − truth| of the air temperature (K) in a reading taken from now on."""
    unit = twin.environment()
    since = time.time()

    def fresh() -> bool:
        try:
            return ifm.environment(max_age=2.0, strict=False).received > since
        except DeviceError:
            return False

    _wait_until(fresh, "a fresh reading")
    reading = ifm.environment(max_age=2.0, strict=False)
    truth = AmbientModel(ENV_SEED, twin.config.ambient).at(reading.timestamp - unit["origin"])
    expected = truth.air_temperature_c + unit["sensor_offsets"]["air_temperature"] + 273.15
    return abs(reading.air_temperature_k - expected)


def test_the_driver_vs_truth_check_fails_on_a_wrong_environment_byte_order(env_twin, monkeypatch):
    from drivers.interferometer import _can  # the driver's module, patched here only

    _, twin = env_twin
    entry = {**twin.station_entry("socketcand"), "layout": {"environment_rate": 20.0}}
    bound = 0.0006
    with create_interferometer(entry, name="interferometer") as ifm:
        assert _environment_error(ifm, twin) <= bound
        original = _can.decode_environment_air

        def big_endian(device, can_id, data):
            frame = original(device, can_id, data)
            code = int.from_bytes(bytes(data[0:2]), "big")
            return dataclasses.replace(frame, air_temperature_k=code / 1000 + 273.15)

        with monkeypatch.context() as patch:
            patch.setattr(_can, "decode_environment_air", big_endian)
            assert _environment_error(ifm, twin) > bound, "a swapped byte order went unnoticed"
        assert _environment_error(ifm, twin) <= bound
