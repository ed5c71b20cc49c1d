"""The measurement core: pure functions and small typed dataclasses (numpy, scipy, OpenCV).

No I/O, no devices, no simulation. SI units throughout (metres, radians, seconds).
"""

__version__ = "0.1.0"
