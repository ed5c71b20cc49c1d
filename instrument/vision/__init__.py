"""Image → cross: pre-processing, IGCF sub-pixel stripe centres, bisquare line fits (method.md §2).

Main entry points :func:`locate_cross` (one frame; with ``prior=`` the last result, it tracks the
cross instead of searching the whole frame) and :func:`locate_crosses` (several frames at once, e.g.
the three cameras of one trigger; a stream passes the same :class:`VisionWorkspace` to every call);
the building blocks are public too:
:func:`igcf_centers` (vectorised IGCF over many cross-sections), :func:`fit_line_bisquare`
(robust line fit) and :func:`find_stripes` (coarse stripe detection).
"""

from instrument.vision._detect import CoarseLine, Detection, find_stripes
from instrument.vision._igcf import SectionCentres, half_window_for_width, igcf_centers
from instrument.vision._linefit import LineFit, fit_line_bisquare
from instrument.vision._locate import locate_cross, locate_crosses
from instrument.vision._types import CrossMeasurement, CrossNotFound, StripeLine
from instrument.vision._workspace import VisionWorkspace

__all__ = [
    "CoarseLine",
    "CrossMeasurement",
    "CrossNotFound",
    "Detection",
    "LineFit",
    "SectionCentres",
    "StripeLine",
    "VisionWorkspace",
    "find_stripes",
    "fit_line_bisquare",
    "half_window_for_width",
    "igcf_centers",
    "locate_cross",
    "locate_crosses",
]
