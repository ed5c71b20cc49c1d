"""Robot controllers: the ``Robot`` interface, the motion envelope, and adapters."""

from collections.abc import Mapping
from typing import Any

from drivers.robot._envelope import MotionEnvelope
from drivers.robot._interface import (
    EmergencyStop,
    MoveFailed,
    ProgramStopped,
    ProtectiveStop,
    Robot,
    RobotState,
)
from drivers.robot._ur import URRobot, create_ur_robot

ADAPTERS = {"ur_rtde": create_ur_robot}


def create(config: Mapping[str, Any], *, name: str = "robot") -> Robot:
    """Build the robot adapter that ``config["adapter"]`` names (``ur_rtde``); the other keys are
    the adapter's settings (see ``URRobot``)."""
    adapter = dict(config).get("adapter")
    if adapter not in ADAPTERS:
        raise ValueError(f"robot {name!r}: unknown adapter {adapter!r}; expected one of {sorted(ADAPTERS)}")
    return ADAPTERS[adapter](config, name=name)


__all__ = [
    "EmergencyStop",
    "MotionEnvelope",
    "MoveFailed",
    "ProgramStopped",
    "ProtectiveStop",
    "Robot",
    "RobotState",
    "URRobot",
    "create",
]
