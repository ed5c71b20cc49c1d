"""The rotary table interface every adapter implements. Angles in radians, speeds in rad/s."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from drivers._errors import DeviceFault, MotionRefused


class TableFault(DeviceFault):
    """The table reports an alarm or error of its own (drive fault, following error, servo off, ...)."""


class CommandRefused(MotionRefused):
    """The table received a command and refused its value (a target beyond its soft limits, a speed
    out of range): nothing moved, and the table is as healthy as before (Modbus exception 3, GCS
    errors 7 and 17)."""


@dataclass(frozen=True)
class TableState:
    in_position: bool
    moving: bool
    homed: bool
    fault: str | None  # None when healthy, else the device's own alarm/error text or code
    position: float  # rad, as reported by the table's encoder


@runtime_checkable
class RotaryTable(Protocol):
    name: str

    def open(self) -> None:
        """Connect and make the table usable (every wait bounded): servo on and, if unreferenced, the
        reference move (unless the settings say ``reference_on_open: false``). Raises
        ``DeviceConnectionError``, ``DeviceTimeout`` or ``TableFault`` naming the step that failed."""
        ...

    def close(self) -> None:
        """Release the connection (also after a failed or no ``open()``; calling it twice is harmless)."""
        ...

    def __enter__(self) -> RotaryTable: ...

    def __exit__(self, *exc: object) -> None: ...

    def home(self, timeout: float = 30.0) -> None: ...

    def move_absolute(self, angle: float, speed: float | None = None) -> None:
        """Start a move; returns at once. Use ``wait_in_position``."""
        ...

    def move_relative(self, delta: float, speed: float | None = None) -> None: ...

    def wait_in_position(self, timeout: float = 30.0) -> float:
        """Block until the table reports in position; returns the position (rad)."""
        ...

    def position(self) -> float: ...

    def stop(self) -> None: ...

    def state(self) -> TableState: ...
