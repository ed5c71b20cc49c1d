"""Robot controllers: the ``Robot`` interface, the motion envelope, the settings and adapters.

``create(settings, name=..., envelope=...)`` builds the adapter that ``settings.adapter`` names
(``ur_rtde``, ``abb_rws``) with the station's ``MotionEnvelope``; it is not opened yet (call
``open()`` or use it as a context manager).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from drivers._settings import SettingsUnion
from drivers.robot._abb import ABBRobot, MotorsOff, RapidExecutionError
from drivers.robot._envelope import MotionEnvelope
from drivers.robot._interface import (
    EmergencyStop,
    MoveFailed,
    ProgramStopped,
    ProtectiveStop,
    Robot,
    RobotIdentity,
    RobotState,
)
from drivers.robot._settings import ABBRwsSettings, RobotSettings, URRtdeSettings
from drivers.robot._ur import URRobot

_SETTINGS_UNION: SettingsUnion[RobotSettings] = SettingsUnion(RobotSettings, "robot")
ADAPTERS = tuple(_SETTINGS_UNION.models)


def create(settings: RobotSettings | Mapping[str, Any], *, name: str = "robot", envelope: MotionEnvelope) -> Robot:
    """The robot adapter for ``settings`` (a ``RobotSettings`` model, or a mapping validated as one).

    Parameters
    ----------
    settings : RobotSettings or mapping
        The station file's ``devices.robot`` entry.
    name : str
        Device name used in every error.
    envelope : MotionEnvelope
        The station's motion limits, checked before any motion is sent.

    Raises
    ------
    SettingsError
        For a mapping that is not valid settings (one line naming the adapter and the setting).
    """
    checked = _SETTINGS_UNION.validate(settings, name=name)
    if isinstance(checked, ABBRwsSettings):
        return ABBRobot(checked, name=name, envelope=envelope)
    return URRobot(checked, name=name, envelope=envelope)


__all__ = [
    "ADAPTERS",
    "ABBRobot",
    "ABBRwsSettings",
    "EmergencyStop",
    "MotionEnvelope",
    "MotorsOff",
    "MoveFailed",
    "ProgramStopped",
    "ProtectiveStop",
    "RapidExecutionError",
    "Robot",
    "RobotIdentity",
    "RobotSettings",
    "RobotState",
    "URRobot",
    "URRtdeSettings",
    "create",
]
