"""The UR twin's controller: the shared controller core (``sim_devices.arm.ArmController``) with
the UR5e arm and the UR twin's seeded streams. See ``sim_devices/arm/_controller.py`` for the cycle,
the servos, the truth and the rule for what the controller reports."""

from __future__ import annotations

from collections.abc import Callable

from sim_devices.arm import (
    RUNTIME_PLAYING,
    RUNTIME_STOPPED,
    SAFETY_BIT_ESTOP,
    SAFETY_BIT_PROTECTIVE,
    ArmController,
    CycleState,
)
from sim_devices.faults import FaultPlan
from sim_devices.ur import _kinematics as kin
from sim_devices.ur._config import URTwinConfig

__all__ = ["RUNTIME_PLAYING", "RUNTIME_STOPPED", "SAFETY_BIT_ESTOP", "SAFETY_BIT_PROTECTIVE", "CycleState",
           "URController"]


class URController(ArmController):
    """A UR e-Series controller core: the shared ``ArmController`` with the UR5e arm."""

    def __init__(self, world, config: URTwinConfig, faults: FaultPlan,
                 on_disconnect: Callable[[], None] | None = None) -> None:
        super().__init__(world, config, faults, on_disconnect, kinematics=kin.UR5E, stream_label="ur")
