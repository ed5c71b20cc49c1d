"""Set-ups: what must be true of the cell before a step is measured, as small typed objects.

A step names the set-up it needs; the engine establishes it whenever it differs from the
current one, so the operator is asked only when the set-up changes (per axis, in the shipped
calibrations). Each set-up knows how to bring the cell there through the station's ``Operator``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from drivers.rotary_table import RotaryTable
from procedures.kinds._parameters import AxisName
from procedures.station import Operator

ON_ROBOT = "robot"  # the Operator's name for the OPR on the flange (``mount_opr("robot")``)


class SetupCell(Protocol):
    """The part of a station a set-up may use (``StationRuntime`` is one)."""

    @property
    def operator(self) -> Operator: ...

    @property
    def table(self) -> RotaryTable: ...


class Setup(Protocol):
    """What a step needs of the cell.

    ``mount`` is where the OPR sits, in the Operator's words (``"robot"``, ``"table:x"``);
    ``after_motion`` says the set-up can only be made once the step's motion has brought the OPR
    to its place; ``str()`` is the label in the run's events (``robot``, ``align:x``, ``table:x``).
    """

    @property
    def mount(self) -> str: ...

    @property
    def after_motion(self) -> bool: ...

    def establish(self, previous: Setup | None, cell: SetupCell) -> None:
        """Bring the cell from ``previous`` (None: unknown, the OPR taken to be on the robot) to this set-up."""
        ...


def _remount(previous: Setup | None, target: Setup, cell: SetupCell) -> None:
    """Ask the operator to move the OPR only when it has to change place."""
    where = previous.mount if previous is not None else ON_ROBOT
    if where != target.mount:
        cell.operator.mount_opr(target.mount)


@dataclass(frozen=True)
class OprOnRobot:
    """The OPR on the robot flange: the cell's resting set-up, in which every run starts and ends."""

    @property
    def mount(self) -> str:
        return ON_ROBOT

    @property
    def after_motion(self) -> bool:
        return False

    def establish(self, previous: Setup | None, cell: SetupCell) -> None:
        _remount(previous, self, cell)

    def __str__(self) -> str:
        return "robot"


@dataclass(frozen=True)
class InterferometerAligned:
    """The OPR on the robot and the interferometer's beam along M's ``axis``.

    Made after the step's motion: the operator aims the head at the reflector where it stands,
    i.e. at the first point of the line.
    """

    axis: AxisName

    @property
    def mount(self) -> str:
        return ON_ROBOT

    @property
    def after_motion(self) -> bool:
        return True

    def establish(self, previous: Setup | None, cell: SetupCell) -> None:
        _remount(previous, self, cell)
        cell.operator.align_interferometer(self.axis)

    def __str__(self) -> str:
        return f"align:{self.axis}"


@dataclass(frozen=True)
class OprOnTable:
    """The OPR on the rotary table, the table's axis along M's ``axis`` through M's origin.

    With ``home_table`` the table is homed (within ``home_timeout_s``) if it reports it is not.
    """

    axis: AxisName
    home_table: bool = True
    home_timeout_s: float = 60.0

    @property
    def mount(self) -> str:
        return f"table:{self.axis}"

    @property
    def after_motion(self) -> bool:
        return False

    def establish(self, previous: Setup | None, cell: SetupCell) -> None:
        _remount(previous, self, cell)
        if self.home_table and not cell.table.state().homed:
            cell.table.home(timeout=self.home_timeout_s)

    def __str__(self) -> str:
        return f"table:{self.axis}"


RESTING_SETUP = OprOnRobot()
