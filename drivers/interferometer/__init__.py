"""Laser interferometers: the ``Interferometer`` interface, the settings, the frame layout and adapters.

``create(settings, name=...)`` builds the adapter that ``settings.adapter`` names: ``socketcand``
(a socketcand daemon over TCP) or ``slcan`` (a Lawicel USB-CAN adapter), both ``CanInterferometer``
reading the feed described by a ``FrameLayout``. It is not opened yet: call ``open()`` or use it
as a context manager.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from drivers._settings import SettingsUnion
from drivers.interferometer._can import CanInterferometer
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
    return CanInterferometer(_SETTINGS_UNION.validate(settings, name=name), name=name)


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
