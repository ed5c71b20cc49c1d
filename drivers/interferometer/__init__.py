"""Laser interferometers: the ``Interferometer`` interface, the settings, the frame layout and adapters.

``create(settings, name=...)`` builds the adapter that ``settings.adapter`` names: ``socketcand``
(a socketcand daemon over TCP) or ``slcan`` (a Lawicel USB-CAN adapter), both ``CanInterferometer``
reading the feed described by a ``FrameLayout``. It is not opened yet: call ``open()`` or use it
as a context manager.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from drivers._extras import load_adapter
from drivers._settings import SettingsUnion
from drivers.interferometer._feed import CanSample
from drivers.interferometer._interface import (
    BeamInterrupted,
    DatumLost,
    EnvironmentReading,
    FeedGap,
    Interferometer,
    Sample,
)
from drivers.interferometer._layout import FrameLayout, StatusFrame, crc8_j1850, frame_crc
from drivers.interferometer._settings import HeadOptics, InterferometerSettings, SlcanSettings, SocketcandSettings

if TYPE_CHECKING:
    from drivers.interferometer._can import CanInterferometer


def __getattr__(name: str) -> Any:
    if name == "CanInterferometer":
        return _can_interferometer("interferometer", "socketcand")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _can_interferometer(device: str, adapter: str) -> Any:
    """``CanInterferometer``, imported with python-can when first needed (drivers._extras)."""
    return load_adapter("drivers.interferometer._can", "CanInterferometer", device=device, adapter=adapter,
                        libraries=("can",), extra="interferometer")


_SETTINGS_UNION: SettingsUnion[InterferometerSettings] = SettingsUnion(InterferometerSettings, "interferometer")
ADAPTERS = tuple(_SETTINGS_UNION.models)


def create(settings: InterferometerSettings | Mapping[str, Any], *, name: str = "interferometer") -> Interferometer:
    """The interferometer adapter for ``settings`` (a model, or a mapping validated as one).

    Parameters
    ----------
    settings : InterferometerSettings or mapping
        The station file's ``devices.interferometer`` entry.
    name : str
        Device name used in every error.

    Raises
    ------
    SettingsError
        For a mapping that is not valid settings (one line naming the adapter and the setting).
    """
    checked = _SETTINGS_UNION.validate(settings, name=name)
    interferometer: Interferometer = _can_interferometer(name, checked.adapter)(checked, name=name)
    return interferometer


__all__ = [
    "ADAPTERS",
    "BeamInterrupted",
    "CanInterferometer",
    "CanSample",
    "DatumLost",
    "EnvironmentReading",
    "FeedGap",
    "FrameLayout",
    "HeadOptics",
    "Interferometer",
    "InterferometerSettings",
    "Sample",
    "SlcanSettings",
    "SocketcandSettings",
    "StatusFrame",
    "crc8_j1850",
    "create",
    "frame_crc",
]
