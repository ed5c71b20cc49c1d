"""The camera twins and the optical bench they image.

``OpticalBench`` is the true optics of the station (screens, the OPR's laser fans, each camera's
homography, distortion, vignetting and noise), drawn from the seed and ``OpticsConfig``;
``Renderer`` draws a camera's image of the laser crosses at a pose; ``CameraFileTwin`` keeps one
BMP per camera up to date for pylon's camera emulator (and serves streaming acquisition through
``StreamServer``); ``SimCamera`` is the same cameras in-process behind the ``drivers.camera``
interface. See docs/cameras.md.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from sim_devices.camera._optics import AXIS_NAMES, FANS, IDEAL_OPTICS, OpticalBench, OpticsConfig
    from sim_devices.camera._renderer import Renderer
    from sim_devices.camera._stamp import stamp_image
    from sim_devices.camera._stream import TICKS_PER_SECOND, CameraClock, StreamConfig, StreamServer, exposure_poses
    from sim_devices.camera._twin import CameraFileTwin, SimCamera

# Each module loads on first use of one of its names: the cell's supervisor and the other twins need
# the bench (NumPy only), not the renderer's SciPy or the camera twin's driver interface (pydantic),
# and every twin process pays its imports at every cell start.
_LAZY = {
    **dict.fromkeys(("AXIS_NAMES", "FANS", "IDEAL_OPTICS", "OpticalBench", "OpticsConfig"), "_optics"),
    "Renderer": "_renderer",
    "stamp_image": "_stamp",
    **dict.fromkeys(("TICKS_PER_SECOND", "CameraClock", "StreamConfig", "StreamServer", "exposure_poses"), "_stream"),
    **dict.fromkeys(("CameraFileTwin", "SimCamera"), "_twin"),
}


def __getattr__(name: str) -> Any:
    """A public name of a module not loaded yet: load it (once) and keep the name here."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


__all__ = ["AXIS_NAMES", "FANS", "IDEAL_OPTICS", "TICKS_PER_SECOND", "CameraClock", "CameraFileTwin", "OpticalBench",
           "OpticsConfig", "Renderer", "SimCamera", "StreamConfig", "StreamServer", "stamp_image", "exposure_poses"]
