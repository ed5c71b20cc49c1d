"""The Modbus register map of a rotary-table servo drive, kept in configuration.

The default follows the style of an Applied Motion ST10-Q-NE drive (holding registers, 0-based
addresses; the drive's manual counts from 40001): alarm code, status code, 32-bit encoder position,
32-bit absolute position command, velocity / acceleration settings and a command ("control") register
that takes an opcode. See ``docs/rotary_table.md`` for the table.

Only the addresses, word order, scaling and bit/opcode numbers live here; both the driver and the
twin read them from the same configuration, and a test runs both on a non-default map.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Literal

from drivers._config import checked_fields


@dataclass(frozen=True)
class StatusBits:
    """Bit numbers in the status register (ST10-style status code; ``homed`` is our addition)."""

    enabled: int = 0
    drive_fault: int = 2
    in_position: int = 3
    moving: int = 4
    stopping: int = 6
    alarm: int = 9
    homing: int = 10
    homed: int = 13


@dataclass(frozen=True)
class AlarmBits:
    """Bit numbers in the alarm register, with the operator text of each."""

    position_limit: int = 0
    ccw_limit: int = 1
    cw_limit: int = 2
    over_temperature: int = 3
    over_voltage: int = 5
    over_current: int = 8
    following_error: int = 10  # "position error" on an ST10
    encoder_fault: int = 11
    command_refused: int = 14  # a move was commanded while the drive could not execute it

    def describe(self, word: int) -> str:
        names = [f.name.replace("_", " ") for f in fields(self) if word >> getattr(self, f.name) & 1]
        return ", ".join(names) if names else f"alarm 0x{word:04x}"


@dataclass(frozen=True)
class Opcodes:
    """Values written to the control register (ST10 "command opcode" style)."""

    move_absolute: int = 0x67  # FP: feed to the position in the position-command register
    move_relative: int = 0x66  # FL: feed by the (signed) distance in the position-command register
    home: int = 0x6E  # seek the reference mark; the counter is zero there
    stop: int = 0xE1  # SK: decelerate and stop
    enable: int = 0x9F  # ME
    disable: int = 0x9E  # MD
    alarm_reset: int = 0xBA  # AR


@dataclass(frozen=True)
class RegisterMap:
    """Addresses (0-based holding registers) and scaling of the drive.

    ``counts_per_rev`` scales the encoder and position registers; velocities are in
    1/``velocity_units_per_rev_s`` rev/s and accelerations in 1/``accel_units_per_rev_s2`` rev/s²
    (an ST10 uses 0.25 rpm = 1/240 rev/s and 1/6 rev/s²).
    """

    alarm: int = 0
    status: int = 1
    encoder_position: int = 2  # 32-bit signed, counts (read only)
    position_command: int = 4  # 32-bit signed, counts (target of move_absolute, distance of move_relative)
    velocity: int = 6  # unsigned 16-bit, move speed
    acceleration: int = 7  # unsigned 16-bit, acceleration and deceleration
    actual_velocity: int = 8  # signed 16-bit, read only
    control: int = 124  # opcode register (40125 on an ST10)
    word_order: Literal["big", "little"] = "big"  # which 16-bit word of a 32-bit value comes first
    counts_per_rev: int = 16_777_216  # 2**24: 0.077 arc-seconds per count
    velocity_units_per_rev_s: float = 240.0
    accel_units_per_rev_s2: float = 6.0
    status_bits: StatusBits = field(default_factory=StatusBits)
    alarm_bits: AlarmBits = field(default_factory=AlarmBits)
    opcodes: Opcodes = field(default_factory=Opcodes)

    # ------------------------------------------------------------------------ conversions
    def counts_to_rad(self, counts: int) -> float:
        return counts * 2.0 * math.pi / self.counts_per_rev

    def rad_to_counts(self, angle: float) -> int:
        return int(round(angle * self.counts_per_rev / (2.0 * math.pi)))

    def rad_s_to_velocity(self, speed: float) -> int:
        return int(round(speed / (2.0 * math.pi) * self.velocity_units_per_rev_s))

    def velocity_to_rad_s(self, units: int) -> float:
        return units / self.velocity_units_per_rev_s * 2.0 * math.pi

    def rad_s2_to_accel(self, accel: float) -> int:
        return int(round(accel / (2.0 * math.pi) * self.accel_units_per_rev_s2))

    def accel_to_rad_s2(self, units: int) -> float:
        return units / self.accel_units_per_rev_s2 * 2.0 * math.pi

    def split32(self, value: int) -> list[int]:
        """A signed 32-bit value as two registers in the configured word order."""
        raw = value & 0xFFFFFFFF
        words = [raw >> 16, raw & 0xFFFF]
        return words if self.word_order == "big" else words[::-1]

    def join32(self, words: list[int] | tuple[int, ...]) -> int:
        high, low = (words[0], words[1]) if self.word_order == "big" else (words[1], words[0])
        raw = (high << 16) | low
        return raw - (1 << 32) if raw & 0x80000000 else raw

    def name_of(self, address: int) -> str:
        """Operator name of a register address (for error messages)."""
        for name in ("alarm", "status", "encoder_position", "position_command", "velocity", "acceleration",
                     "actual_velocity", "control"):
            start = getattr(self, name)
            width = 2 if name in ("encoder_position", "position_command") else 1
            if start <= address < start + width:
                return f"{name.replace('_', ' ')} register 0x{address:04x}"
        return f"register 0x{address:04x}"

    # ------------------------------------------------------------------------ configuration
    @classmethod
    def from_config(cls, data: Mapping[str, Any] | RegisterMap | None) -> RegisterMap:
        """Build from a mapping (station YAML); unknown keys are an error, nested groups may be partial."""
        if isinstance(data, RegisterMap):
            return data
        data = checked_fields(cls, data, "register map")
        nested = {"status_bits": StatusBits, "alarm_bits": AlarmBits, "opcodes": Opcodes}
        for key, kind in nested.items():
            if key in data and not isinstance(data[key], kind):
                data[key] = kind(**checked_fields(kind, data[key], f"register map {key}"))
        result = cls(**data)
        if result.word_order not in ("big", "little"):
            raise ValueError(f"register map word_order must be 'big' or 'little', got {result.word_order!r}")
        return result

    def to_config(self) -> dict[str, Any]:
        return asdict(self)
