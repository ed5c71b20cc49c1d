"""GigE Vision twin cameras: each one a camera of the sensor module on its own loopback address.

``GigeCameraTwin`` speaks GVCP (UDP 3956) and GVSP with its own codec (written from the GigE
Vision protocol, never shared with a driver), serves its own GenICam XML, and streams every
triggered frame live, rendered at the true OPR pose of its exposure. ``GigeTwinHost`` is the same
camera as a ``TwinProcess`` host (one process per camera, as a cell runs it). Standalone:
``python -m sim_devices.gige --host 127.0.0.N``. See docs/cameras.md, "GigE Vision".
"""

from sim_devices.gige._camera import GigeCameraTwin, GigeTwinConfig, check_loopback, pixel_bytes
from sim_devices.gige._features import FEATURE, FEATURES, PIXEL_FORMATS, genicam_xml
from sim_devices.gige._host import GigeTwinHost

__all__ = ["FEATURE", "FEATURES", "PIXEL_FORMATS", "GigeCameraTwin", "GigeTwinConfig", "GigeTwinHost",
           "check_loopback", "genicam_xml", "pixel_bytes"]
