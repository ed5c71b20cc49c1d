"""Result types of ``instrument.vision`` (shared with the pose solver and the CLI)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class CrossNotFound(ValueError):
    """The image holds no usable cross: none, one stripe only, two crosses, or a stripe too short
    to fit. The message says which."""


@dataclass(frozen=True)
class StripeLine:
    """One fitted stripe centre line, in pixels (x = column, y = row).

    Attributes
    ----------
    point : (2,) array
        A point on the line (the centroid of the sections used).
    direction : (2,) array
        Unit direction; points to +x for the horizontal stripe, to +y for the vertical one.
    sections : int
        Cross-sections whose IGCF centre entered the line fit.
    residual_rms : float
        RMS perpendicular distance of those centres from the line, px (bisquare-weighted points).
    saturated_sections : int
        Sections where the saturation rule removed pixels.
    """

    point: np.ndarray
    direction: np.ndarray
    sections: int
    residual_rms: float
    saturated_sections: int


@dataclass(frozen=True)
class CrossMeasurement:
    """A located cross.

    Attributes
    ----------
    center : (2,) array
        Intersection of the two lines, (x, y) px; pixel (row r, col c) is centred at (c, r).
    angle : float
        Rotation from the image axes, rad, positive from +x toward +y: (φh + φv) / 2.
    horizontal, vertical : StripeLine
    perpendicularity : float
        φv − φh, rad: the non-perpendicularity of the two stripes seen in the image.
    peak_level : float
        Highest grey level on the stripes.
    search : str
        How the stripes were found: ``"full"`` (coarse detection on the whole frame, no prior
        given), ``"tracked"`` (searched only near the prior's lines) or ``"fallback"`` (a prior
        was given but lost, so the full search ran; ``lost_reason`` says why).
    lost_reason : str or None
        Why the prior was declared lost (``search == "fallback"``), else None.
    """

    center: np.ndarray
    angle: float
    horizontal: StripeLine
    vertical: StripeLine
    perpendicularity: float
    peak_level: float
    search: str = "full"
    lost_reason: str | None = None
