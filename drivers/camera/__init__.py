"""Cameras: the ``Camera`` interface, the pylon adapter, the triplet and the factory.

The simulated in-process camera lives in ``sim_devices.camera_twin.SimCamera`` (drivers never
import sim_devices)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from drivers.camera._interface import Camera, Frame, GrabFailed, Roi, TriggeredCamera
from drivers.camera._pylon import SATURATION, PylonCamera, ensure_emulated_cameras
from drivers.camera._triplet import CameraTriplet

ADAPTERS = {"pylon": PylonCamera}


def create(config: Mapping[str, Any], *, name: str) -> Camera:
    """A camera from its station-file entry: ``config["adapter"]`` picks the adapter, the rest
    are that adapter's keyword settings (see ``PylonCamera``). Not opened yet."""
    settings = dict(config)
    adapter = settings.pop("adapter", None)
    if adapter not in ADAPTERS:
        raise ValueError(f"camera {name}: unknown adapter {adapter!r}; expected one of {sorted(ADAPTERS)}")
    cls = ADAPTERS[adapter]
    known = set(
        cls.__init__.__code__.co_varnames[: cls.__init__.__code__.co_argcount + cls.__init__.__code__.co_kwonlyargcount]
    )
    unknown = set(settings) - known - {"self"}
    if unknown:
        raise ValueError(f"camera {name}: unknown setting(s) {sorted(unknown)} for adapter {adapter!r}")
    settings.setdefault("name", name)
    return cls(**settings)


def create_triplet(
    configs: Mapping[str, Mapping[str, Any]], *, name: str = "cameras", retries: int = 2
) -> CameraTriplet:
    """The station file's ``devices.cameras`` mapping (x, y, z) → a ``CameraTriplet`` (not opened)."""
    return CameraTriplet({key: create(cfg, name=key) for key, cfg in configs.items()}, retries=retries, name=name)


__all__ = [
    "ADAPTERS", "Camera", "CameraTriplet", "Frame", "GrabFailed", "PylonCamera", "Roi", "SATURATION",
    "TriggeredCamera", "create", "create_triplet", "ensure_emulated_cameras",
]
