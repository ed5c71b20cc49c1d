"""Cameras: the ``Camera`` interface, the settings, the pylon adapter, the triplet and the factories.

``create(settings, name=...)`` builds the adapter that ``settings.adapter`` names (``pylon``,
``aravis``); it is not opened yet. The simulated in-process camera lives in ``sim_devices.camera.SimCamera``
(drivers never import sim_devices).
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from drivers.camera._interface import Camera, Frame, GrabFailed, Roi, TriggeredCamera

if TYPE_CHECKING:
    from drivers._settings import SettingsUnion
    from drivers.camera._aravis import AravisCamera, aravis_available
    from drivers.camera._aravis_action import ActionGroup
    from drivers.camera._pylon import SATURATION, PylonCamera, ensure_emulated_cameras
    from drivers.camera._settings import ActionSettings, AravisSettings, CameraSettings, PylonSettings
    from drivers.camera._stamp import EmbeddedStamp, read_stamp
    from drivers.camera._stream import FrameStream, StreamStats, StreamTriple
    from drivers.camera._triplet import CameraTriplet

    ADAPTERS: tuple[str, ...]

# The interface loads at once; each adapter's module, and the settings (pydantic), on first use of one
# of its names: a process that only needs ``Frame`` (a camera twin) does not pay for them.
_LAZY = {
    **dict.fromkeys(("AravisCamera", "aravis_available"), "_aravis"),
    "ActionGroup": "_aravis_action",
    **dict.fromkeys(("SATURATION", "PylonCamera", "ensure_emulated_cameras"), "_pylon"),
    **dict.fromkeys(("ActionSettings", "AravisSettings", "CameraSettings", "PylonSettings"), "_settings"),
    **dict.fromkeys(("EmbeddedStamp", "read_stamp"), "_stamp"),
    **dict.fromkeys(("FrameStream", "StreamStats", "StreamTriple"), "_stream"),
    "CameraTriplet": "_triplet",
}
_settings_union: SettingsUnion[CameraSettings] | None = None


def _union() -> SettingsUnion[CameraSettings]:
    global _settings_union
    if _settings_union is None:
        from drivers._settings import SettingsUnion
        from drivers.camera._settings import CameraSettings

        _settings_union = SettingsUnion(CameraSettings, "camera")
    return _settings_union


def __getattr__(name: str) -> Any:
    """A public name of a module not loaded yet: load it (once) and keep the name here."""
    if name == "ADAPTERS":
        value: Any = tuple(_union().models)
    elif name in _LAZY:
        value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


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
    from drivers.camera._aravis import AravisCamera
    from drivers.camera._pylon import PylonCamera
    from drivers.camera._settings import AravisSettings

    checked = _union().validate(settings, name=name)
    if isinstance(checked, AravisSettings):
        return AravisCamera(checked, name=name)
    return PylonCamera(checked, name=name)


def create_triplet(
    settings: Mapping[str, CameraSettings | Mapping[str, Any]], *, name: str = "cameras", retries: int = 2
) -> CameraTriplet:
    """The station file's ``devices.cameras`` (x, y, z) as a ``CameraTriplet`` (not opened)."""
    from drivers.camera._triplet import CameraTriplet

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
