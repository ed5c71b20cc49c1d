"""The head's side of the frame layout: encoding what it sends, decoding the host's commands.

Written separately from the driver's decoder (only the ``FrameLayout`` settings are shared), so a
byte-order or scaling slip on one side shows up as wrong readings in the tests.
See ``drivers/interferometer/_layout.py`` / ``docs/interferometer.md`` for the byte map.
"""

from __future__ import annotations

import struct

BEAM_OK, SIGNAL_LOW, DATUM_SET, OVERRANGE = 0x01, 0x02, 0x04, 0x08
OPCODE_DATUM = 0x01
OPCODE_SYNC = 0x02
AXIS_CODES = {"x": 0, "y": 1, "z": 2}
INT40_MAX = (1 << 39) - 1


def _crc8_table() -> list[int]:
    table = []
    for value in range(256):
        crc = value
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) if crc & 0x80 else (crc << 1)
            crc &= 0xFF
        table.append(crc)
    return table


_TABLE = _crc8_table()


def crc8(data: bytes) -> int:
    """CRC-8/SAE-J1850: poly 0x1D, init 0xFF, xor-out 0xFF (table driven)."""
    crc = 0xFF
    for byte in data:
        crc = _TABLE[crc ^ byte]
    return crc ^ 0xFF


def seal(can_id: int, body: bytes) -> bytes:
    """Append the CRC over the id (2 bytes, big-endian) and the 7 body bytes."""
    assert len(body) == 7
    return body + bytes([crc8(struct.pack(">H", can_id) + body)])


def displacement_frame(can_id: int, counts: int, counter: int, status: int, signal: float) -> bytes:
    counts = max(-INT40_MAX, min(INT40_MAX, counts))
    nibble = max(0, min(15, round(signal * 15)))
    body = (counts & ((1 << 40) - 1)).to_bytes(5, "little") + bytes([counter & 0xFF, (status & 0x0F) | nibble << 4])
    return seal(can_id, body)


def status_frame(can_id: int, status: int, signal: float, axis: str, generation: int, heartbeat: int) -> bytes:
    strength = max(0, min(65535, round(signal * 65535)))
    body = bytes([status & 0x0F]) + struct.pack("<H", strength) + bytes(
        [AXIS_CODES[axis], generation & 0xFF, 0, heartbeat & 0xFF])
    return seal(can_id, body)


def reply_frame(can_id: int, opcode: int, token: int, result: int, generation: int) -> bytes:
    return seal(can_id, bytes([opcode & 0xFF, token & 0xFF, result & 0xFF, generation & 0xFF, 0, 0, 0]))


def parse_command(can_id: int, data: bytes) -> tuple[int, int] | None:
    """``(opcode, token)`` of a well-formed command frame, else None (the head ignores it)."""
    if len(data) != 8 or seal(can_id, bytes(data[:7]))[7] != data[7]:
        return None
    return data[0], data[1]


# Environmental unit (docs/interferometer.md): temperatures in mK above 0 °C, pressure in Pa above
# 60 kPa, humidity in 0.01 % RH, all uint16 little-endian; 0xFFFF where there is no reading (a sensor
# not fitted, faulty or out of its range: the last two also set the sensor's fault bit).
NO_READING = 0xFFFF
PRESSURE_BASE_PA = 60_000


def _field(value: float | None, scale: float, base: float = 0.0) -> int | None:
    """The uint16 for ``value`` (None: no reading; outside the field: None too)."""
    if value is None:
        return None
    code = round((value - base) * scale)
    return code if 0 <= code < NO_READING else None


def environment_frames(air_id: int, material_id: int, cycle: int, air_temperature_c: float | None,
                       pressure_pa: float | None, humidity_percent: float | None,
                       materials_c: list[float | None], faulty: set[str]) -> list[tuple[int, bytes]]:
    """The air frame and the material frame of one measuring cycle (``cycle`` mod 16 in both).

    ``materials_c`` has one entry per fitted sensor (up to three); a sensor named in ``faulty``
    (``air_temperature``, ``pressure``, ``humidity``, ``material1``..``material3``) reports a fault.
    """
    def encode(values: list[tuple[str, float | None, float, float]]) -> tuple[bytes, int]:
        body, faults = b"", 0
        for bit, (name, value, scale, base) in enumerate(values):
            code = None if name in faulty else _field(value, scale, base)
            if code is None and (value is not None or name in faulty):
                faults |= 1 << bit  # fitted but no good reading
            body += struct.pack("<H", NO_READING if code is None else code)
        return body, faults

    counter = (cycle & 0x0F) << 4
    air, air_faults = encode([("air_temperature", air_temperature_c, 1000.0, 0.0),
                              ("pressure", pressure_pa, 1.0, PRESSURE_BASE_PA),
                              ("humidity", humidity_percent, 100.0, 0.0)])
    fitted = list(materials_c) + [None] * (3 - len(materials_c))
    material, material_faults = encode([(f"material{i + 1}", value, 1000.0, 0.0) for i, value in enumerate(fitted)])
    return [(air_id, seal(air_id, air + bytes([counter | air_faults]))),
            (material_id, seal(material_id, material + bytes([counter | material_faults])))]
