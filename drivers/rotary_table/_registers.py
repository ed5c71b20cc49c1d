"""The Modbus register map of a rotary-table servo drive, kept in configuration.

The default follows the style of an Applied Motion ST10-Q-NE drive (holding registers, 0-based
addresses; the drive's manual counts from 40001): alarm code, status code, 32-bit encoder position,
32-bit absolute position command, velocity / acceleration settings and a command ("control") register
that takes an opcode. See ``docs/rotary_table.md`` for the table.

Only the addresses, word order, scaling and bit/opcode numbers live here: they are data a station
file may carry (``register_map:`` under a Modbus table), validated by these pydantic models. The
encoding helpers below are the driver's; the twin reads the same data and encodes with its own code.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

Address = Annotated[int, Field(ge=0, le=0xFFFF, description="0-based holding-register address")]
Bit = Annotated[int, Field(ge=0, le=15, description="bit number in a 16-bit register")]
Opcode = Annotated[int, Field(ge=0, le=0xFFFF, description="value written to the control register")]


class _Format(BaseModel):
    """A part of the register map: unknown keys are errors, values never change."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class StatusBits(_Format):
    """Bit numbers in the status register (ST10-style status code; ``homed`` is our addition)."""

    enabled: Bit = 0
    drive_fault: Bit = 2
    in_position: Bit = 3
    moving: Bit = 4
    stopping: Bit = 6
    alarm: Bit = 9
    homing: Bit = 10
    homed: Bit = 13


class AlarmBits(_Format):
    """Bit numbers in the alarm register, with the operator text of each."""

    position_limit: Bit = 0
    ccw_limit: Bit = 1
    cw_limit: Bit = 2
    over_temperature: Bit = 3
    over_voltage: Bit = 5
    over_current: Bit = 8
    following_error: Bit = 10  # "position error" on an ST10
    encoder_fault: Bit = 11
    command_refused: Bit = 14  # a move was commanded while the drive could not execute it

    def describe(self, word: int) -> str:
        """The alarms set in ``word`` in words (``"following error, encoder fault"``)."""
        names = [name.replace("_", " ") for name in type(self).model_fields if word >> getattr(self, name) & 1]
        return ", ".join(names) if names else f"alarm 0x{word:04x}"


class Opcodes(_Format):
    """Values written to the control register (ST10 "command opcode" style)."""

    move_absolute: Opcode = 0x67  # FP: feed to the position in the position-command register
    move_relative: Opcode = 0x66  # FL: feed by the (signed) distance in the position-command register
    home: Opcode = 0x6E  # seek the reference mark; the counter is zero there
    stop: Opcode = 0xE1  # SK: decelerate and stop
    enable: Opcode = 0x9F  # ME
    disable: Opcode = 0x9E  # MD
    alarm_reset: Opcode = 0xBA  # AR


_REGISTERS_32 = ("encoder_position", "position_command")
_REGISTERS = ("alarm", "status", "encoder_position", "position_command", "velocity", "acceleration",
              "actual_velocity", "control")


class RegisterMap(_Format):
    """Addresses (0-based holding registers) and scaling of the drive.

    ``counts_per_rev`` scales the encoder and position registers; velocities are in
    1/``velocity_units_per_rev_s`` rev/s and accelerations in 1/``accel_units_per_rev_s2`` rev/s²
    (an ST10 uses 0.25 rpm = 1/240 rev/s and 1/6 rev/s²). Any subset of fields may be given; the
    others keep the ST10-style defaults.
    """

    alarm: Address = 0
    status: Address = 1
    encoder_position: Annotated[Address, Field(description="32-bit signed, counts (read only); 2 registers")] = 2
    position_command: Annotated[
        Address, Field(description="32-bit signed, counts: target of move_absolute; 2 registers")
    ] = 4
    velocity: Annotated[Address, Field(description="unsigned 16-bit move speed")] = 6
    acceleration: Annotated[Address, Field(description="unsigned 16-bit acceleration and deceleration")] = 7
    actual_velocity: Annotated[Address, Field(description="signed 16-bit, read only")] = 8
    control: Annotated[Address, Field(description="opcode register (40125 on an ST10)")] = 124
    word_order: Literal["big", "little"] = Field(
        "big", description="which 16-bit word of a 32-bit value comes first (big: the high word)"
    )
    counts_per_rev: int = Field(16_777_216, gt=0, description="encoder counts per revolution (2**24: 0.077 arcsec)")
    velocity_units_per_rev_s: float = Field(240.0, gt=0, description="velocity register units per rev/s")
    accel_units_per_rev_s2: float = Field(6.0, gt=0, description="acceleration register units per rev/s²")
    status_bits: StatusBits = Field(default_factory=StatusBits)
    alarm_bits: AlarmBits = Field(default_factory=AlarmBits)
    opcodes: Opcodes = Field(default_factory=Opcodes)

    @model_validator(mode="after")
    def _registers_apart(self) -> RegisterMap:
        taken: dict[int, str] = {}
        for name in _REGISTERS:
            start = getattr(self, name)
            for address in range(start, start + (2 if name in _REGISTERS_32 else 1)):
                if address in taken:
                    raise ValueError(f"{name} and {taken[address]} both use register {address}")
                taken[address] = name
        return self

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
        for name in _REGISTERS:
            start = getattr(self, name)
            width = 2 if name in _REGISTERS_32 else 1
            if start <= address < start + width:
                return f"{name.replace('_', ' ')} register 0x{address:04x}"
        return f"register 0x{address:04x}"
