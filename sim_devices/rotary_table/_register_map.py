"""The drive's side of the Modbus register map: the twin's own reading of ``docs/rotary_table.md``.

Written from the documented table, not from the driver: only the *data* (addresses, word order,
scaling, bit and opcode numbers, with the same documented keys) may come from the same YAML, so a
word-order or scaling slip on either side fails a test instead of cancelling out.

The documented encoding (ST10-Q-NE style holding registers, 0-based addresses):

- 32-bit values (``encoder_position``, ``position_command``) are two's complement over two
  consecutive registers; ``word_order: big`` puts the high 16-bit word at the lower address,
  ``little`` the low word. Positions are in counts, ``counts_per_rev`` per revolution.
- ``velocity`` (u16) and ``actual_velocity`` (s16) are in 1/``velocity_units_per_rev_s`` rev/s
  (1/240 rev/s = 0.25 rpm by default); ``acceleration`` (u16) in 1/``accel_units_per_rev_s2`` rev/s².
- ``status``, ``alarm``: one bit per condition; ``control`` takes an opcode.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Literal

from sim_devices._config import checked_fields

WordOrder = Literal["big", "little"]
TURN = 2.0 * math.pi  # rad per revolution


@dataclass(frozen=True)
class DriveStatusBits:
    """Bit numbers of the status register (documented defaults)."""

    enabled: int = 0
    drive_fault: int = 2
    in_position: int = 3
    moving: int = 4
    stopping: int = 6
    alarm: int = 9
    homing: int = 10
    homed: int = 13


@dataclass(frozen=True)
class DriveAlarmBits:
    """Bit numbers of the alarm register (documented defaults)."""

    position_limit: int = 0
    ccw_limit: int = 1
    cw_limit: int = 2
    over_temperature: int = 3
    over_voltage: int = 5
    over_current: int = 8
    following_error: int = 10
    encoder_fault: int = 11
    command_refused: int = 14


@dataclass(frozen=True)
class DriveOpcodes:
    """Opcodes the control register accepts (documented defaults)."""

    move_absolute: int = 0x67
    move_relative: int = 0x66
    home: int = 0x6E
    stop: int = 0xE1
    enable: int = 0x9F
    disable: int = 0x9E
    alarm_reset: int = 0xBA


_GROUPS: dict[str, type] = {"status_bits": DriveStatusBits, "alarm_bits": DriveAlarmBits, "opcodes": DriveOpcodes}


@dataclass(frozen=True)
class DriveRegisterMap:
    """Addresses, word order and scaling of the simulated drive (the ``register_map`` settings).

    Build it from a mapping with ``from_config`` (any subset of the documented keys; nested groups
    may be partial). Every method converts between SI values and register words as the drive does.
    """

    alarm: int = 0
    status: int = 1
    encoder_position: int = 2
    position_command: int = 4
    velocity: int = 6
    acceleration: int = 7
    actual_velocity: int = 8
    control: int = 124
    word_order: WordOrder = "big"
    counts_per_rev: int = 16_777_216
    velocity_units_per_rev_s: float = 240.0
    accel_units_per_rev_s2: float = 6.0
    status_bits: DriveStatusBits = field(default_factory=DriveStatusBits)
    alarm_bits: DriveAlarmBits = field(default_factory=DriveAlarmBits)
    opcodes: DriveOpcodes = field(default_factory=DriveOpcodes)

    def __post_init__(self) -> None:
        if self.word_order not in ("big", "little"):
            raise ValueError(f"register map: word_order must be 'big' or 'little', got {self.word_order!r}")
        if not (isinstance(self.counts_per_rev, int) and self.counts_per_rev > 0):
            raise ValueError(f"register map: counts_per_rev must be a positive integer, got {self.counts_per_rev!r}")
        for name in ("velocity_units_per_rev_s", "accel_units_per_rev_s2"):
            if not getattr(self, name) > 0:
                raise ValueError(f"register map: {name} must be > 0, got {getattr(self, name)!r}")
        for name, (start, width) in self.spans().items():
            if not (isinstance(start, int) and 0 <= start and start + width <= 0x10000):
                raise ValueError(f"register map: {name} address {start!r} is not a register address (0..65535)")
        ordered = sorted((start, start + width, name) for name, (start, width) in self.spans().items())
        for (_, end, first), (start, _, second) in zip(ordered, ordered[1:]):
            if start < end:
                raise ValueError(f"register map: {first} and {second} overlap")
        for group in (self.status_bits, self.alarm_bits):
            for item in fields(group):
                if not 0 <= getattr(group, item.name) <= 15:
                    raise ValueError(f"register map: bit {item.name} must be 0..15, got {getattr(group, item.name)!r}")

    # ------------------------------------------------------------------------ configuration
    @classmethod
    def from_config(cls, data: Mapping[str, Any] | DriveRegisterMap | None) -> DriveRegisterMap:
        """From the ``register_map`` mapping of a cell or twin configuration (None: the defaults)."""
        if isinstance(data, DriveRegisterMap):
            return data
        settings = checked_fields(cls, data, "register map")
        for key, group in _GROUPS.items():
            if key in settings:
                settings[key] = group(**checked_fields(group, settings[key], f"register map {key}"))
        return cls(**settings)

    def to_config(self) -> dict[str, Any]:
        return asdict(self)

    def spans(self) -> dict[str, tuple[int, int]]:
        """``name: (first address, number of registers)`` of every mapped register."""
        return {"alarm": (self.alarm, 1), "status": (self.status, 1), "encoder_position": (self.encoder_position, 2),
                "position_command": (self.position_command, 2), "velocity": (self.velocity, 1),
                "acceleration": (self.acceleration, 1), "actual_velocity": (self.actual_velocity, 1),
                "control": (self.control, 1)}

    # ------------------------------------------------------------------------ 32-bit values
    def words_of_s32(self, value: int) -> tuple[int, int]:
        """A signed 32-bit value as the two register words, in address order."""
        high, low = struct.unpack(">HH", struct.pack(">i", value))
        return (high, low) if self.word_order == "big" else (low, high)

    def s32_of_words(self, first: int, second: int) -> int:
        """The signed 32-bit value held by two registers, given in address order."""
        high, low = (first, second) if self.word_order == "big" else (second, first)
        (value,) = struct.unpack(">i", struct.pack(">HH", high & 0xFFFF, low & 0xFFFF))
        return int(value)

    # ------------------------------------------------------------------------ scaling
    def speed_word(self, speed: float) -> int:
        """``velocity`` register (u16) for a speed in rad/s (saturating)."""
        units = round(speed / TURN * self.velocity_units_per_rev_s)
        return min(max(units, 0), 0xFFFF)

    def actual_velocity_word(self, velocity: float) -> int:
        """``actual_velocity`` register (s16 as a register word) for a signed velocity in rad/s (saturating)."""
        units = min(max(round(velocity / TURN * self.velocity_units_per_rev_s), -0x8000), 0x7FFF)
        (word,) = struct.unpack(">H", struct.pack(">h", units))
        return int(word)

    def speed_of_word(self, word: int) -> float:
        """rad/s of a ``velocity`` register value."""
        return word / self.velocity_units_per_rev_s * TURN

    def acceleration_word(self, acceleration: float) -> int:
        """``acceleration`` register (u16) for rad/s² (saturating)."""
        units = round(acceleration / TURN * self.accel_units_per_rev_s2)
        return min(max(units, 0), 0xFFFF)

    def acceleration_of_word(self, word: int) -> float:
        """rad/s² of an ``acceleration`` register value."""
        return word / self.accel_units_per_rev_s2 * TURN
