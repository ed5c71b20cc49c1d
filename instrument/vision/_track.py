"""The tracking path of ``locate_cross``: a prior (the last result) replaces the coarse detection.

While the robot moves, consecutive frames show the cross a few pixels (at most a few tens) from
where it was. Instead of block-averaging and Hough-transforming the whole frame, each stripe is
re-acquired in a band of ±``search_px`` around its prior line, on about ``REACQUIRE_SECTIONS``
cross-sections spread along it: the brightest pixel of each sampled section, then a trimmed line fit. That coarse
line feeds the same band → IGCF → bisquare pipeline as the full search (``_bands``), so the result
is as precise as the full search's.

The prior is **lost** (and the caller falls back to the full search) when, for either stripe:

1. fewer than ``MIN_FOUND_FRACTION`` of the sampled sections inside the frame show a peak that
   stands out (≥ ``MIN_PEAK_SIGMAS`` noise σ above the band's background and ≥ ``PEAK_FRACTION`` of
   the upper-quartile peak) at least ``EDGE_MARGIN`` px inside the search band — the stripe has
   left the band, dimmed or vanished;
2. fewer than ``MIN_INLIER_FRACTION`` of those peaks lie within ``INLIER_PX`` of one straight line
   — what the band holds is not one stripe;
3. the fine fit fails (too few usable sections), or keeps fewer than ``MIN_SECTIONS_KEPT`` of the
   prior's sections — the stripe was only partly found.

A second cross appearing in the frame is not looked for while tracking (the full search reports
it); it is caught only if it disturbs the fit enough to trip one of the rules above.
"""

from __future__ import annotations

import numpy as np

from instrument.vision._bands import CrossJob, kind, measure_crosses
from instrument.vision._detect import CoarseLine
from instrument.vision._linefit import _median
from instrument.vision._types import CrossMeasurement, CrossNotFound

TRACK_SEARCH_PX = 24  # default half-width of the re-acquisition band around each prior line, px
REACQUIRE_SECTIONS = 150  # about this many cross-sections are sampled to re-acquire a stripe
MAX_REACQUIRE_STRIDE = 16
MIN_FOUND_FRACTION = 0.5
MIN_PEAK_SIGMAS = 6.0
PEAK_FRACTION = 0.25
MIN_INLIER_FRACTION = 0.7
INLIER_PX = 2.0
MIN_SECTIONS_KEPT = 0.5
EDGE_MARGIN = 3  # a brightest pixel this close to the search band's edge does not count
EDGE_SAMPLE_ROWS = 4  # rows at each end of the search band that sample its background


def prior_lines(prior) -> tuple[CoarseLine, CoarseLine]:
    """The two stripe lines of a prior ``CrossMeasurement`` as coarse lines (horizontal, vertical)."""
    try:
        h_point, h_dir = np.asarray(prior.horizontal.point, float), np.asarray(prior.horizontal.direction, float)
        v_point, v_dir = np.asarray(prior.vertical.point, float), np.asarray(prior.vertical.direction, float)
    except AttributeError:
        raise TypeError(
            f"prior must be the CrossMeasurement of the previous frame (or None), got {type(prior).__name__}"
        ) from None
    if h_point.shape != (2,) or v_point.shape != (2,) or not np.all(np.isfinite([*h_point, *v_point])):
        raise ValueError("prior: the stripe lines' points must be finite (x, y) pixel coordinates")
    if not (abs(h_dir[0]) > 1e-9 and abs(v_dir[1]) > 1e-9):
        raise ValueError("prior: a stripe direction is degenerate (horizontal stripe with no x part, or "
                         "vertical stripe with no y part)")
    h_slope = float(h_dir[1] / h_dir[0])  # y = a + b·x
    v_slope = float(v_dir[0] / v_dir[1])  # x = a + b·y
    horizontal = CoarseLine(False, float(h_point[1] - h_slope * h_point[0]), h_slope, 0)
    vertical = CoarseLine(True, float(v_point[0] - v_slope * v_point[1]), v_slope, 0)
    return horizontal, vertical


def _reacquire(flat, shape, line: CoarseLine, other: CoarseLine, search: int) -> tuple[CoarseLine, float] | str:
    """The stripe near ``line`` again, to about a pixel, with the band's background; or why not."""
    rows, cols = shape
    n_sections, across_len = (rows, cols) if line.vertical else (cols, rows)
    # every stride-th section: ~REACQUIRE_SECTIONS of them, whose brightest pixels (±0.5 px each)
    # place the line to a few hundredths of a pixel — far more than the fine stage's band needs
    stride = min(max(n_sections // REACQUIRE_SECTIONS, 1), MAX_REACQUIRE_STRIDE)
    s = np.arange(stride // 2, n_sections, stride)
    position = line.at(s)
    # leave out the crossing: sections where the other stripe runs through the search band
    reach = search * (1.0 + abs(other.slope)) + search
    keep = (np.abs(s - other.at(position)) > reach) & (position > -search) & (position < across_len - 1 + search)
    s, position = s[keep], position[keep]
    name = kind(line.vertical)
    if len(s) < 4:
        return f"{name} stripe: its prior line runs out of the frame"
    width = 2 * search + 1
    base = np.rint(position).astype(np.intp) - search  # first pixel of each sampled section's band
    step, stride = (1, cols) if line.vertical else (cols, 1)  # flat-index steps across / along
    first, last = min(base[0], base[-1]), max(base[0], base[-1]) + width - 1  # base is monotonic in s
    if first >= 0 and last < across_len:  # the usual case: the whole search band lies in the frame
        inside = None
        values = flat.take(np.add.outer(base * step + s * stride, np.arange(width) * step))
        sample = np.concatenate([values[:, :EDGE_SAMPLE_ROWS].ravel(), values[:, -EDGE_SAMPLE_ROWS:].ravel()])
    else:
        across = base[:, None] + np.arange(width)[None, :]
        inside = (across >= 0) & (across < across_len)
        values = flat.take(np.clip(across, 0, across_len - 1) * step + (s * stride)[:, None])
        edge = np.r_[0:EDGE_SAMPLE_ROWS, width - EDGE_SAMPLE_ROWS : width]
        sample = values[:, edge][inside[:, edge]]
    if len(sample) < 8:
        return f"{name} stripe: its search band lies off the frame"
    background = _median(sample)
    noise = max(1.4826 * _median(np.abs(sample - background)), 0.5)
    if inside is not None:  # pixels off the frame read as background
        values[~inside] = np.asarray(background).astype(values.dtype)
    peak_index = values.argmax(axis=1)
    contrast = values[np.arange(len(s)), peak_index] - background
    standing = contrast >= MIN_PEAK_SIGMAS * noise
    n_standing = int(np.count_nonzero(standing))
    if n_standing >= 4:  # a few hot pixels must not set the level: the upper quartile of the peaks
        upper_quartile = int(0.75 * (n_standing - 1))
        typical = float(np.partition(contrast[standing], upper_quartile)[upper_quartile])
        standing &= contrast >= PEAK_FRACTION * typical
    margin = EDGE_MARGIN
    found = standing & (peak_index >= margin) & (peak_index < width - margin)
    n_found = int(np.count_nonzero(found))
    n_inside = len(s) if inside is None else int(np.count_nonzero(inside[:, search]))
    if n_found < max(4, MIN_FOUND_FRACTION * n_inside):
        return (
            f"{name} stripe not found within ±{search} px of its prior line "
            f"({n_found} of {n_inside} sampled sections show it)"
        )
    # the brightest pixel is good to ±0.5 px; a line through a few hundred of them to ~0.05 px,
    # far inside what the band around the coarse line needs
    centre = (base[found] + peak_index[found]).astype(float)
    along = s[found].astype(float)
    intercept, slope = _line(along, centre)
    inliers = np.abs(centre - (intercept + slope * along)) <= INLIER_PX
    n_inliers = int(np.count_nonzero(inliers))
    if n_inliers < MIN_INLIER_FRACTION * n_found:
        return (
            f"{name} stripe: the peaks near its prior line do not lie on one straight line "
            f"({n_inliers} of {n_found} within {INLIER_PX:g} px)"
        )
    if n_inliers < n_found:  # refit without the stray peaks (hot pixels, a reflection)
        intercept, slope = _line(along[inliers], centre[inliers])
    return CoarseLine(line.vertical, intercept, slope, n_found), background


def _line(u: np.ndarray, v: np.ndarray) -> tuple[float, float]:
    """Least-squares v = a + b·u (u spread: the sampled sections)."""
    u_mean, v_mean = float(u.mean()), float(v.mean())
    du = u - u_mean
    slope = float(du @ (v - v_mean)) / float(du @ du)
    return v_mean - slope * u_mean, slope


def reacquire(flat, shape, prior, search) -> tuple[CoarseLine, CoarseLine, float] | str:
    """Both stripes near ``prior``'s lines: (horizontal, vertical, background), or why the prior is lost."""
    h_prior, v_prior = prior_lines(prior)
    horizontal = _reacquire(flat, shape, h_prior, v_prior, search)
    if isinstance(horizontal, str):
        return horizontal
    vertical = _reacquire(flat, shape, v_prior, h_prior, search)
    if isinstance(vertical, str):
        return vertical
    (h_line, h_background), (v_line, v_background) = horizontal, vertical
    return h_line, v_line, 0.5 * (h_background + v_background)


def lost_after_fit(measured: CrossMeasurement | CrossNotFound, prior) -> str | None:
    """Rule 3 of the module docstring: why the fine fit shows the prior lost, or None."""
    if isinstance(measured, CrossNotFound):
        return f"tracked fit failed: {measured}"
    for name, new, old in (
        ("near-horizontal", measured.horizontal, prior.horizontal),
        ("near-vertical", measured.vertical, prior.vertical),
    ):
        if new.sections < MIN_SECTIONS_KEPT * old.sections:
            return f"{name} stripe: only {new.sections} usable sections, the prior had {old.sections}"
    return None


def track_cross(flat, shape, saturation, prior, half_window, min_sections, search) -> CrossMeasurement | str:
    """The cross found near ``prior``'s lines, or the reason the prior is lost (a string)."""
    lines = reacquire(flat, shape, prior, search)
    if isinstance(lines, str):
        return lines
    horizontal, vertical, background = lines
    job = CrossJob(flat, shape, horizontal, vertical, background, saturation, "tracked")
    (measured,) = measure_crosses([job], half_window, min_sections)
    reason = lost_after_fit(measured, prior)
    if reason is not None or isinstance(measured, CrossNotFound):
        return reason or str(measured)
    return measured
