"""Cameras: the ``Camera`` interface, the settings, the pylon adapter, the triplet and the factories.

``create(settings, name=...)`` builds the adapter that ``settings.adapter`` names (``pylon``,
``aravis``); it is not opened yet. The simulated in-process camera lives in ``sim_devices.camera.SimCamera``
(drivers never import sim_devices).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from drivers._settings import SettingsUnion
from drivers.camera._aravis import AravisCamera, aravis_available
from drivers.camera._aravis_action import ActionGroup
from drivers.camera._interface import Camera, Frame, GrabFailed, Roi, TriggeredCamera
from drivers.camera._pylon import SATURATION, PylonCamera, ensure_emulated_cameras
from drivers.camera._settings import ActionSettings, AravisSettings, CameraSettings, PylonSettings
from drivers.camera._stamp import EmbeddedStamp, read_stamp
from drivers.camera._stream import FrameStream, StreamStats, StreamTriple
from drivers.camera._triplet import CameraTriplet

_SETTINGS_UNION: SettingsUnion[CameraSettings] = SettingsUnion(CameraSettings, "camera")
ADAPTERS = tuple(_SETTINGS_UNION.models)


def create(settings: CameraSettings | Mapping[str, Any], *, name: str) -> TriggeredCamera:
    """The camera adapter for ``settings`` (a ``CameraSettings`` model, or a mapping validated as one).

    Parameters
    ----------
    settings : CameraSettings or mapping
        One entry of the station file's ``devices.cameras``.
    name : str
        Device name used in every error.

    Raises
    ------
    SettingsError
        For a mapping that is not valid settings (one line naming the adapter and the setting).
    """
    checked = _SETTINGS_UNION.validate(settings, name=name)
    if isinstance(checked, AravisSettings):
        return AravisCamera(checked, name=name)
    return PylonCamera(checked, name=name)


def create_triplet(
    settings: Mapping[str, CameraSettings | Mapping[str, Any]], *, name: str = "cameras", retries: int = 2
) -> CameraTriplet:
    """The station file's ``devices.cameras`` (x, y, z) as a ``CameraTriplet`` (not opened)."""
    return CameraTriplet({key: create(entry, name=key) for key, entry in settings.items()}, retries=retries, name=name)


__all__ = [
    "ADAPTERS",
    "ActionGroup",
    "ActionSettings",
    "AravisCamera",
    "AravisSettings",
    "Camera",
    "CameraSettings",
    "CameraTriplet",
    "EmbeddedStamp",
    "Frame",
    "FrameStream",
    "GrabFailed",
    "PylonCamera",
    "PylonSettings",
    "Roi",
    "SATURATION",
    "StreamStats",
    "StreamTriple",
    "TriggeredCamera",
    "aravis_available",
    "create",
    "create_triplet",
    "ensure_emulated_cameras",
    "read_stamp",
]
