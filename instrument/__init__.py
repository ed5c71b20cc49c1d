"""The measurement core: pure functions and small typed dataclasses (numpy, scipy, OpenCV).

No I/O, no devices, no simulation. SI units throughout (metres, radians, seconds). The conventions the
whole house shares are here once: ``ARCSEC`` (one arc-second in rad), ``COMPONENTS`` (the order of a (6,)
pose in M) and ``SCREENS`` (the three screens).
"""

from instrument._conventions import ARCSEC, COMPONENTS, SCREENS

__version__ = "0.1.0"
__all__ = ["ARCSEC", "COMPONENTS", "SCREENS", "__version__"]
