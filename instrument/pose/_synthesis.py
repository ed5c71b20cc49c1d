"""Forward model down to pixels: the ``CrossMeasurement`` a perfect (or noisy) vision would return.

Used by tests, benchmarks and what-if studies; it is the exact inverse of the mapping that
``solve_pose`` applies to measurements.
"""

from __future__ import annotations

import numpy as np

from instrument.pose._errors import CrossOffScreenError
from instrument.pose._geometry import SCREEN_NAMES, Geometry, Screen
from instrument.pose._lines import FANS, ScreenLine, intersect, predict_lines
from instrument.pose._rotation import Pose
from instrument.vision._types import CrossMeasurement, StripeLine


def _fit_pixel_line(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    centroid = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centroid, full_matrices=False)
    direction = vt[0]
    normal = np.array([-direction[1], direction[0]])
    residual = (points - centroid) @ normal
    return centroid, direction, float(np.sqrt(np.mean(residual**2)))


def _stripe_pixels(line: ScreenLine, center: np.ndarray, screen: Screen, half_length: float, rng, noise_px: float):
    # One sample per ~pixel along the stripe, like one IGCF section per image column/row.
    ends = screen.screen_to_pixels(
        np.array([center - half_length * line.direction, center + half_length * line.direction])
    )
    count = max(int(np.linalg.norm(ends[1] - ends[0])), 8)
    steps = np.linspace(-half_length, half_length, count)
    pixels = screen.screen_to_pixels(center + steps[:, None] * line.direction)
    if screen.size_px is not None:
        width, height = screen.size_px
        inside = (pixels[:, 0] >= 0) & (pixels[:, 0] <= width - 1) & (pixels[:, 1] >= 0) & (pixels[:, 1] <= height - 1)
        pixels = pixels[inside]
        if len(pixels) < 8:
            raise CrossOffScreenError(f"screen {screen.name!r}: the stripe leaves the image")
    if noise_px > 0.0:
        _, direction, _ = _fit_pixel_line(pixels)
        normal = np.array([-direction[1], direction[0]])
        pixels = pixels + rng.normal(0.0, noise_px, size=(len(pixels), 1)) * normal
    return pixels


def predict_measurements(
    pose: Pose,
    geometry: Geometry,
    *,
    half_length: float = 0.07,
    noise_px: float = 0.0,
    rng: np.random.Generator | None = None,
) -> dict[str, CrossMeasurement]:
    """The three ``CrossMeasurement`` a pose produces, as a perfect line-fitting vision reports them.

    Parameters
    ----------
    pose : Pose
        OPR pose in M.
    geometry : Geometry
    half_length : float
        Half the stripe length sampled on each side of the cross centre, m on the screen (clipped
        to the image when the screen knows ``size_px``).
    noise_px : float
        Standard deviation of each section centre across the stripe, px (0: exact lines).
    rng : numpy Generator, optional
        Source of the noise (seed it for reproducible results).
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    lines = predict_lines(pose, geometry)
    out: dict[str, CrossMeasurement] = {}
    for name in SCREEN_NAMES:
        screen = geometry.screens[name]
        first, second = (lines[name][fan] for fan in FANS[name])
        center = intersect(first, second)
        fitted = []
        for line in (first, second):
            pixels = _stripe_pixels(line, center, screen, half_length, rng, noise_px)
            point, direction, rms = _fit_pixel_line(pixels)
            fitted.append((point, direction, rms, len(pixels)))
        # "Horizontal" in the image is whichever stripe runs closer to the image x axis.
        horizontal_index = 0 if abs(fitted[0][1][0]) >= abs(fitted[1][1][0]) else 1
        h, v = fitted[horizontal_index], fitted[1 - horizontal_index]
        dh = h[1] if h[1][0] >= 0 else -h[1]
        dv = v[1] if v[1][1] >= 0 else -v[1]
        horizontal = StripeLine(h[0], dh, h[3], h[2], 0)
        vertical = StripeLine(v[0], dv, v[3], v[2], 0)
        center_px = intersect(ScreenLine(h[0], dh), ScreenLine(v[0], dv))
        phi_h = float(np.arctan2(dh[1], dh[0]))
        phi_v = float(np.arctan2(-dv[0], dv[1]))
        out[name] = CrossMeasurement(center_px, (phi_h + phi_v) / 2.0, horizontal, vertical, phi_v - phi_h, 200.0)
    return out
