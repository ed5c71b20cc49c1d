"""The conventions every package of the house shares, defined once: angle units, pose components, screens.

``COMPONENTS`` orders a (6,) pose in the measurement frame M: ``[x, y, z, a, b, c]`` (metres, radians;
a, b, c = α, θ, γ of R = Rz(γ)·Ry(θ)·Rx(α), ISO 9283's a, b, c). ``SCREENS`` names the three screens
(and the camera that images each), one per axis of M. ``ARCSEC`` is one arc-second in radians: figures
stay SI inside and are shown in arc-seconds at the edge.
"""

import math

ARCSEC = math.pi / (180.0 * 3600.0)
COMPONENTS = ("x", "y", "z", "a", "b", "c")
SCREENS = ("x", "y", "z")
