"""Robot controllers: the ``Robot`` interface, the motion envelope, and adapters."""

from drivers.robot._envelope import MotionEnvelope
from drivers.robot._interface import (
    EmergencyStop,
    MoveFailed,
    ProgramStopped,
    ProtectiveStop,
    Robot,
    RobotState,
)

__all__ = [
    "EmergencyStop",
    "MotionEnvelope",
    "MoveFailed",
    "ProgramStopped",
    "ProtectiveStop",
    "Robot",
    "RobotState",
]
