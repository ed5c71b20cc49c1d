"""The CAN frame layout of the interferometer feed, and its decoder.

No interferometer vendor publishes a CAN layout, so this one is ours (documented in
``docs/interferometer.md``). Everything that a different head or firmware could change (ids,
scaling, rates) lives in ``FrameLayout``, a pydantic model a station file may carry; the byte
positions below are the protocol itself, encoded and decoded here by the driver (the twin has
its own code for them).

Every frame is 8 bytes, standard 11-bit id, little-endian, and ends with a CRC-8/SAE-J1850
(poly 0x1D, init 0xFF, xor-out 0xFF) computed over the id (2 bytes, big-endian) followed by
data bytes 0..6, so a frame with a flipped bit *or* a wrong id fails the check.

Displacement (``displacement_id``, default 0x181, ``sample_rate`` Hz)::

    0..4  int40  displacement in ``resolution`` metres from the datum (two's complement)
    5     uint8  sample counter, +1 per sample, wraps at 256
    6     uint8  status: bit0 beam OK, bit1 signal low, bit2 datum set, bit3 overrange,
                 bits 4..7 signal strength in 1/15 steps
    7     uint8  CRC-8

Status / heartbeat (``status_id``, default 0x281, ``status_rate`` Hz)::

    0     uint8  status bits as above (bits 0..3)
    1..2  uint16 signal strength, 0..65535 = 0..1
    3     uint8  beam axis the head is aimed along: 0 = x, 1 = y, 2 = z of M
    4     uint8  datum generation (+1 at every datum)
    5     uint8  reserved, 0
    6     uint8  heartbeat counter
    7     uint8  CRC-8

The head executes a command between two samples and sends the reply before the next
displacement frame, so every displacement frame after a reply was sampled after the command
(``sync`` is used as a barrier: "only samples taken from now on").

Command (host → head, ``command_id``, default 0x601) and reply (``reply_id``, default 0x581)::

    command: 0 opcode (1 = set datum, 2 = sync), 1 token, 2..6 zero, 7 CRC-8
    reply:   0 opcode, 1 token, 2 result (0 = done, 1 = refused: beam not OK, 2 = unknown opcode),
             3 datum generation, 4..6 zero, 7 CRC-8

Environmental unit, one measuring cycle every 1/``environment_rate`` s: the air frame
(``environment_air_id``, default 0x381), then the material frame (``environment_material_id``,
default 0x481), both carrying the cycle counter. Every value is a uint16, little-endian, 0xFFFF
when there is no reading (sensor not fitted, or faulty: then its fault bit is set)::

    air:      0..1 air temperature, 0.001 K above 273.15 K; 2..3 pressure, 1 Pa above 60 000 Pa;
              4..5 relative humidity, 0.01 %; 6 bits 0..2 fault (air temperature, pressure,
              humidity), bit 3 zero, bits 4..7 cycle counter (+1 per cycle, mod 16); 7 CRC-8
    material: 0..1, 2..3, 4..5 material temperatures 1..3, 0.001 K above 273.15 K;
              6 bits 0..2 fault (material 1..3), bit 3 zero, bits 4..7 cycle counter; 7 CRC-8
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, WithJsonSchema, model_validator

from drivers._errors import ProtocolError

OPCODE_DATUM = 0x01
OPCODE_SYNC = 0x02  # no action; the reply marks the point after which every sample is newer
REPLY_DONE = 0
REPLY_REFUSED = 1

STATUS_BEAM_OK = 0x01
STATUS_SIGNAL_LOW = 0x02
STATUS_DATUM_SET = 0x04
STATUS_OVERRANGE = 0x08

AXIS_NAMES = ("x", "y", "z")
NO_READING = 0xFFFF
MILLIKELVIN = 1000  # temperature counts per kelvin
ZERO_CELSIUS_MK = 273_150  # temperatures count from 0 °C
PRESSURE_BASE_PA = 60_000  # pressure counts (1 Pa) from 60 kPa
HUMIDITY_COUNTS = 10_000  # relative humidity counts per unit (0.01 %)
AIR_SENSORS = ("air_temperature", "pressure", "humidity")
MATERIAL_SENSORS = ("material1", "material2", "material3")
FRAME_LENGTH = 8
COUNTER_MODULUS = 256
DISPLACEMENT_BITS = 40


def _can_id(value: object) -> object:
    """A CAN id as an int: YAML gives ``0x181`` as an int already, a quoted ``"0x181"`` as text."""
    if isinstance(value, str):
        try:
            return int(value, 0)
        except ValueError:
            raise ValueError(f"{value!r} is not a number (write 0x181 or 385)") from None
    return value


def _standard_id(value: int) -> int:
    if not 0 <= value <= 0x7FF:
        raise ValueError(f"CAN id {value:#x} is not a standard 11-bit id (0..0x7FF)")
    return value


CanId = Annotated[
    int,
    BeforeValidator(_can_id),
    AfterValidator(_standard_id),
    WithJsonSchema({"anyOf": [{"type": "integer", "minimum": 0, "maximum": 0x7FF},
                              {"type": "string", "pattern": "^0[xX][0-9a-fA-F]{1,3}$"}],
                    "description": "standard 11-bit CAN id (0..0x7FF), as a number or a hex string"}),
]


class FrameLayout(BaseModel):
    """Ids, scaling and rates of the feed: data a station file may carry (``layout:``).

    Any subset of fields may be given; ids are ints or hex strings (``"0x181"``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    displacement_id: CanId = 0x181
    status_id: CanId = 0x281
    command_id: CanId = 0x601
    reply_id: CanId = 0x581
    resolution: float = Field(
        1e-10, gt=0, description="metres per count (0.1 nm; the int40 field then spans +-55 m)"
    )
    sample_rate: float = Field(1000.0, gt=0, le=10_000, description="displacement frames per second, Hz")
    status_rate: float = Field(10.0, gt=0, description="heartbeat frames per second, Hz (at most sample_rate)")
    environment_air_id: CanId = 0x381
    environment_material_id: CanId = 0x481
    environment_rate: float = Field(
        1.0, gt=0, description="environmental unit's measuring cycles per second, Hz (at most sample_rate)"
    )

    @model_validator(mode="after")
    def _consistent(self) -> FrameLayout:
        ids = [self.displacement_id, self.status_id, self.command_id, self.reply_id, self.environment_air_id,
               self.environment_material_id]
        if len(set(ids)) != len(ids):
            raise ValueError(f"the six CAN ids must differ, got {[hex(i) for i in ids]}")
        for name in ("status_rate", "environment_rate"):
            if getattr(self, name) > self.sample_rate:
                raise ValueError(f"{name} {getattr(self, name)} Hz is above sample_rate {self.sample_rate} Hz")
        return self

    @property
    def max_counts(self) -> int:
        return 2 ** (DISPLACEMENT_BITS - 1) - 1


def crc8_j1850(data: bytes) -> int:
    """CRC-8/SAE-J1850 (check value of ``b"123456789"`` is 0x4B)."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def frame_crc(can_id: int, data: bytes) -> int:
    """The CRC a frame with this id must carry in byte 7."""
    return crc8_j1850(can_id.to_bytes(2, "big") + bytes(data[:7]))


@dataclass(frozen=True)
class DisplacementFrame:
    counts: int
    counter: int
    status: int

    @property
    def beam_ok(self) -> bool:
        return bool(self.status & STATUS_BEAM_OK)

    @property
    def signal_low(self) -> bool:
        return bool(self.status & STATUS_SIGNAL_LOW)

    @property
    def datum_set(self) -> bool:
        return bool(self.status & STATUS_DATUM_SET)

    @property
    def overrange(self) -> bool:
        return bool(self.status & STATUS_OVERRANGE)

    @property
    def signal_strength(self) -> float:
        return (self.status >> 4) / 15.0


@dataclass(frozen=True)
class StatusFrame:
    status: int
    signal_strength: float
    axis: str
    datum_generation: int
    heartbeat: int


@dataclass(frozen=True)
class ReplyFrame:
    opcode: int
    token: int
    result: int
    datum_generation: int


@dataclass(frozen=True)
class EnvironmentAirFrame:
    air_temperature_k: float  # NaN: no reading
    pressure_pa: float
    relative_humidity: float  # a fraction
    faults: tuple[str, ...]  # sensors reporting a fault
    counter: int  # cycle counter, mod 16


@dataclass(frozen=True)
class EnvironmentMaterialFrame:
    temperatures_k: tuple[float, float, float]  # NaN: no reading
    fitted: tuple[bool, bool, bool]  # a sensor is fitted when it gives a reading or reports a fault
    faults: tuple[str, ...]
    counter: int


def check_frame(device: str, can_id: int, data: bytes, what: str) -> None:
    """Raise ``ProtocolError`` unless ``data`` is a full 8-byte frame with a good CRC."""
    if len(data) != FRAME_LENGTH:
        raise ProtocolError(device, f"decode {what} frame 0x{can_id:03X}",
                            f"{len(data)} data bytes, expected {FRAME_LENGTH}")
    expected = frame_crc(can_id, data)
    if data[7] != expected:
        raise ProtocolError(device, f"decode {what} frame 0x{can_id:03X}",
                            f"CRC mismatch (frame carries 0x{data[7]:02X}, computed 0x{expected:02X})")


def decode_displacement(device: str, can_id: int, data: bytes) -> DisplacementFrame:
    check_frame(device, can_id, data, "displacement")
    counts = int.from_bytes(data[0:5], "little", signed=True)
    return DisplacementFrame(counts=counts, counter=data[5], status=data[6])


def decode_status(device: str, can_id: int, data: bytes) -> StatusFrame:
    check_frame(device, can_id, data, "status")
    if data[3] >= len(AXIS_NAMES):
        raise ProtocolError(device, f"decode status frame 0x{can_id:03X}", f"axis code {data[3]} is not 0, 1 or 2")
    return StatusFrame(
        status=data[0],
        signal_strength=int.from_bytes(data[1:3], "little") / 65535.0,
        axis=AXIS_NAMES[data[3]],
        datum_generation=data[4],
        heartbeat=data[6],
    )


def decode_reply(device: str, can_id: int, data: bytes) -> ReplyFrame:
    check_frame(device, can_id, data, "reply")
    return ReplyFrame(opcode=data[0], token=data[1], result=data[2], datum_generation=data[3])


def _uint16(data: bytes, index: int, counts_per_unit: int, base_counts: int) -> float:
    """Field ``index`` (bytes 2·index, 2·index + 1) as ``(code + base_counts) / counts_per_unit``."""
    code = int.from_bytes(data[2 * index:2 * index + 2], "little")
    return math.nan if code == NO_READING else (code + base_counts) / counts_per_unit


def _faults(status: int, names: tuple[str, ...]) -> tuple[str, ...]:
    return tuple(name for bit, name in enumerate(names) if status >> bit & 1)


def decode_environment_air(device: str, can_id: int, data: bytes) -> EnvironmentAirFrame:
    check_frame(device, can_id, data, "environment air")
    return EnvironmentAirFrame(air_temperature_k=_uint16(data, 0, MILLIKELVIN, ZERO_CELSIUS_MK),
                               pressure_pa=_uint16(data, 1, 1, PRESSURE_BASE_PA),
                               relative_humidity=_uint16(data, 2, HUMIDITY_COUNTS, 0),
                               faults=_faults(data[6], AIR_SENSORS), counter=data[6] >> 4)


def decode_environment_material(device: str, can_id: int, data: bytes) -> EnvironmentMaterialFrame:
    check_frame(device, can_id, data, "environment material")
    temperatures = (_uint16(data, 0, MILLIKELVIN, ZERO_CELSIUS_MK), _uint16(data, 1, MILLIKELVIN, ZERO_CELSIUS_MK),
                    _uint16(data, 2, MILLIKELVIN, ZERO_CELSIUS_MK))
    faults = _faults(data[6], MATERIAL_SENSORS)
    fitted = (not math.isnan(temperatures[0]) or "material1" in faults,
              not math.isnan(temperatures[1]) or "material2" in faults,
              not math.isnan(temperatures[2]) or "material3" in faults)
    return EnvironmentMaterialFrame(temperatures_k=temperatures, fitted=fitted, faults=faults, counter=data[6] >> 4)


def encode_command(command_id: int, opcode: int, token: int) -> bytes:
    body = bytes([opcode & 0xFF, token & 0xFF, 0, 0, 0, 0, 0])
    return body + bytes([frame_crc(command_id, body)])
