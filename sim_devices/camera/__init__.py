"""The camera twins and the optical bench they image.

``OpticalBench`` is the true optics of the station (screens, the OPR's laser fans, each camera's
homography, distortion, vignetting and noise), drawn from the seed and ``OpticsConfig``;
``Renderer`` draws a camera's image of the laser crosses at a pose; ``CameraFileTwin`` keeps one
BMP per camera up to date for pylon's camera emulator (and serves streaming acquisition through
``StreamServer``); ``SimCamera`` is the same cameras in-process behind the ``drivers.camera``
interface. See docs/cameras.md.
"""

from sim_devices.camera._optics import AXIS_NAMES, FANS, IDEAL_OPTICS, OpticalBench, OpticsConfig
from sim_devices.camera._renderer import Renderer
from sim_devices.camera._stamp import stamp_image
from sim_devices.camera._stream import TICKS_PER_SECOND, CameraClock, StreamConfig, StreamServer, exposure_poses
from sim_devices.camera._twin import CameraFileTwin, SimCamera

__all__ = ["AXIS_NAMES", "FANS", "IDEAL_OPTICS", "TICKS_PER_SECOND", "CameraClock", "CameraFileTwin", "OpticalBench",
           "OpticsConfig", "Renderer", "SimCamera", "StreamConfig", "StreamServer", "stamp_image", "exposure_poses"]
