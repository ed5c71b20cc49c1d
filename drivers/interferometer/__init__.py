"""Laser interferometers: the ``Interferometer`` interface and adapters.

``create(config, name=...)`` builds an adapter from a station-file mapping:

- ``{adapter: socketcand, host: 127.0.0.1, port: 29536, channel: can0, layout: {...}}``
- ``{adapter: slcan, port: /dev/ttyACM0, bitrate: 1000000, layout: {...}}``

``layout`` (optional) overrides ``FrameLayout`` fields (ids, resolution, rates). Any further keys
are ``CanInterferometer`` options: ``ring_capacity``, ``open_timeout``, ``open_attempts``,
``stall_timeout``, ``reconnect_interval``, ``command_timeout``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from drivers.interferometer._can import CanInterferometer
from drivers.interferometer._feed import CanSample
from drivers.interferometer._interface import BeamInterrupted, DatumLost, FeedGap, Interferometer, Sample
from drivers.interferometer._layout import FrameLayout, StatusFrame, crc8_j1850, frame_crc

ADAPTERS = ("socketcand", "slcan")

_OPTIONS = {"ring_capacity", "open_timeout", "open_attempts", "stall_timeout", "reconnect_interval",
            "command_timeout"}
_REQUIRED = {"socketcand": {"host", "port"}, "slcan": {"port"}}
_ALLOWED = {"socketcand": {"host", "port", "channel", "layout"} | _OPTIONS,
            "slcan": {"port", "bitrate", "layout"} | _OPTIONS}


def create(config: Mapping[str, Any], *, name: str = "interferometer") -> CanInterferometer:
    """Build (not open) the interferometer adapter described by ``config``.

    Raises ``ValueError`` with a clear message for an unknown adapter or bad keys.
    """
    settings = dict(config)
    adapter = settings.pop("adapter", None)
    if adapter not in ADAPTERS:
        raise ValueError(f"{name}: unknown interferometer adapter {adapter!r}; expected one of {list(ADAPTERS)}")
    missing = _REQUIRED[adapter] - set(settings)
    if missing:
        raise ValueError(f"{name}: adapter {adapter!r} needs {sorted(missing)}")
    unknown = set(settings) - _ALLOWED[adapter]
    if unknown:
        raise ValueError(f"{name}: adapter {adapter!r} does not take {sorted(unknown)}; "
                         f"allowed: {sorted(_ALLOWED[adapter])}")
    if adapter == "socketcand":
        return CanInterferometer.socketcand(name=name, **settings)
    return CanInterferometer.slcan(name=name, **settings)


__all__ = [
    "ADAPTERS",
    "BeamInterrupted",
    "CanInterferometer",
    "CanSample",
    "DatumLost",
    "FeedGap",
    "FrameLayout",
    "Interferometer",
    "Sample",
    "StatusFrame",
    "crc8_j1850",
    "create",
    "frame_crc",
]
