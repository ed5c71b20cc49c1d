"""Twin of the laser interferometer displacement feed (1 kHz over CAN: socketcand and slcan) and
of its environmental unit (air and material sensors, 1 Hz on the same bus).

See ``docs/interferometer.md`` and ``docs/environment.md``. ``InterferometerTwin(world, config)``
embeds in a cell; ``StandaloneInterferometerHost`` runs on its own world in a ``TwinProcess``.
"""

from sim_devices.interferometer._bus import CanBusTiming
from sim_devices.interferometer._config import EnvironmentSensorConfig, FeedLayout, InterferometerTwinConfig
from sim_devices.interferometer._head import HeadReading, InterferometerHead
from sim_devices.interferometer._host import InterferometerTwin, StandaloneInterferometerHost, move_opr
from sim_devices.interferometer._slcan import SLCAN_FOLDER_PREFIX, remove_stale_slcan_folders

__all__ = [
    "CanBusTiming",
    "EnvironmentSensorConfig",
    "FeedLayout",
    "HeadReading",
    "InterferometerHead",
    "InterferometerTwin",
    "InterferometerTwinConfig",
    "SLCAN_FOLDER_PREFIX",
    "StandaloneInterferometerHost",
    "move_opr",
    "remove_stale_slcan_folders",
]
