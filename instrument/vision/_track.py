"""The tracking path of ``locate_cross``: a prior (the last result) replaces the coarse detection.

While the robot moves, consecutive frames show the cross a few pixels (at most a few tens) from
where it was. Instead of block-averaging and Hough-transforming the whole frame, the fine stage's
bands (±``BAND_HALF_WIDTH`` px, ``_bands``) are laid around the prior's two lines and checked
there (:func:`prior_band_verdicts`): the brightest pixel of every section of the band must show the
stripe on one straight line. A stripe within ``MAX_BAND_OFFSET`` of its prior line is measured in
that band as it is — one read of the frame, no separate search; one further off is measured in a
band laid around the line its brightest pixels show; one not cleanly in the band is searched for
within ±``search_px`` of its prior line (:func:`reacquire_stripe`: ~``REACQUIRE_SECTIONS`` sampled
cross-sections, brightest pixel of each, a trimmed line fit). Either way the band → IGCF → bisquare
pipeline is the full search's, so the result is as precise.

The prior is **lost** (and the caller falls back to the full search) when, for either stripe:

1. fewer than ``MIN_FOUND_FRACTION`` of the sampled sections inside the frame show a peak that
   stands out (≥ ``MIN_PEAK_SIGMAS`` noise σ above the band's background and ≥ ``PEAK_FRACTION`` of
   the upper-quartile peak) at least ``EDGE_MARGIN`` px inside the search band — the stripe has
   left the band, dimmed or vanished;
2. fewer than ``MIN_INLIER_FRACTION`` of those peaks lie within ``INLIER_PX`` of one straight line
   — what the band holds is not one stripe;
3. the fine fit fails (too few usable sections), or keeps fewer than ``MIN_SECTIONS_KEPT`` of the
   prior's sections — the stripe was only partly found.

Rules 1–2 are those of the ±``search_px`` search; the check of the band around the prior line
applies the same two (without the upper-quartile rule) and, when they fail, hands the stripe to
that search rather than declaring it lost. A second cross appearing in the frame is not looked for
while tracking (the full search reports it); it is caught only if it disturbs the fit enough to trip
one of the rules above.
"""

from __future__ import annotations

import math

import numpy as np

from instrument.vision._bands import BAND_HALF_WIDTH, SAMPLE_STRIDE, BandPlan, Bands, kind
from instrument.vision._detect import CoarseLine
from instrument.vision._igcf import BrightestRuns
from instrument.vision._linefit import _median
from instrument.vision._strided import across_view
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
MAX_BAND_OFFSET = 2.0  # px: a stripe this close to its prior line is measured in the band around that line


def prior_lines(prior) -> tuple[CoarseLine, CoarseLine]:
    """The two stripe lines of a prior ``CrossMeasurement`` as coarse lines (horizontal, vertical)."""
    try:
        h_point, h_dir, v_point, v_dir = (
            np.asarray(vector, float) for vector in (prior.horizontal.point, prior.horizontal.direction,
                                                     prior.vertical.point, prior.vertical.direction))
    except AttributeError:
        raise TypeError(
            f"prior must be the CrossMeasurement of the previous frame (or None), got {type(prior).__name__}"
        ) from None
    if h_point.shape != (2,) or v_point.shape != (2,) or h_dir.shape != (2,) or v_dir.shape != (2,):
        raise ValueError("prior: the stripe lines' points must be finite (x, y) pixel coordinates")
    (hx, hy), (hdx, hdy), (vx, vy), (vdx, vdy) = (h_point.tolist(), h_dir.tolist(), v_point.tolist(), v_dir.tolist())
    if not all(map(math.isfinite, (hx, hy, vx, vy))):
        raise ValueError("prior: the stripe lines' points must be finite (x, y) pixel coordinates")
    if not (abs(hdx) > 1e-9 and abs(vdy) > 1e-9):
        raise ValueError("prior: a stripe direction is degenerate (horizontal stripe with no x part, or "
                         "vertical stripe with no y part)")
    h_slope = hdy / hdx  # y = a + b·x
    v_slope = vdx / vdy  # x = a + b·y
    return CoarseLine(False, hy - h_slope * hx, h_slope, 0), CoarseLine(True, vx - v_slope * vy, v_slope, 0)


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
        values = across_view(flat, width, step)[base * step + s * stride]
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


def reacquire_stripe(flat, shape, line: CoarseLine, other: CoarseLine, search: int) -> CoarseLine | str:
    """The stripe near ``line`` (within ±``search`` px) to about a pixel, or why the prior is lost."""
    found = _reacquire(flat, shape, line, other, search)
    return found if isinstance(found, str) else found[0]


def prior_band_verdicts(bands: Bands, runs: BrightestRuns, plans: list[BandPlan], lines: list[CoarseLine]):
    """Whether each band, laid around its stripe's prior line, holds the stripe.

    Per stripe: True — the brightest pixels of its sections lie on one line within
    ``MAX_BAND_OFFSET`` of the band's centre (measure the stripe in this band); a ``CoarseLine`` —
    they lie on one line further off (lay the band around that line); False — the stripe is not
    cleanly in the band (rules 1–2 of the module docstring fail there: search ±search_px).
    Every ``SAMPLE_STRIDE``-th section is looked at (a few hundred per stripe, as many as the
    ±search_px search samples): their brightest pixels place the line to a few hundredths of a pixel.
    """
    layout = bands.segments
    sampled, counts, stripe = layout.sampled, layout.sample_counts, layout.sample_stripe
    first = layout.sample_starts[:-1]
    middle_along = np.array([0.5 * (p.along[0] + p.along[-1]) for p in plans])
    u = np.concatenate([p.along[::SAMPLE_STRIDE] for p in plans]) - middle_along[stripe]
    middle = runs.middle[sampled]
    # the run's middle across the stripe, from the prior line (base + BAND_HALF_WIDTH is its rounding)
    offset = middle + np.concatenate([p.base[::SAMPLE_STRIDE] - p.position[::SAMPLE_STRIDE] for p in plans])
    standing = runs.peak[sampled] - bands.background[sampled] >= MIN_PEAK_SIGMAS * bands.noise[stripe]
    standing &= np.abs(middle - BAND_HALF_WIDTH) <= BAND_HALF_WIDTH - EDGE_MARGIN
    found = np.add.reduceat(standing, first)
    a, b = _lines_per_stripe(first, u, offset, standing)
    inliers = standing & (np.abs(offset - (a[stripe] + b[stripe] * u)) <= INLIER_PX)
    n_inliers = np.add.reduceat(inliers, first)
    if np.logical_or.reduce(n_inliers < found):  # refit without the stray peaks (hot pixels, a reflection)
        a, b = _lines_per_stripe(first, u, offset, inliers)
    verdicts: list[bool | CoarseLine] = []
    for j, line in enumerate(lines):
        if found[j] < max(4, MIN_FOUND_FRACTION * counts[j]) or n_inliers[j] < MIN_INLIER_FRACTION * found[j]:
            verdicts.append(False)
        elif abs(a[j]) + abs(b[j]) * 0.5 * (plans[j].along[-1] - plans[j].along[0]) <= MAX_BAND_OFFSET:
            verdicts.append(True)
        else:  # across = line + a + b·(along − middle)
            verdicts.append(CoarseLine(line.vertical, line.intercept + a[j] - b[j] * middle_along[j],
                                       line.slope + b[j], int(found[j])))
    return verdicts


def _lines_per_stripe(first, u, v, use):
    """Least-squares v = a + b·u of each stripe's points where ``use`` (stripe j's points start at
    ``first[j]``): (a, b) arrays."""
    w = use.astype(float)
    wu, wv = w * u, w * v
    sw, su, sv, suu, suv = (np.add.reduceat(x, first) for x in (w, wu, wv, wu * u, wu * v))
    det = sw * suu - su * su
    b = np.where(det > 0, (sw * suv - su * sv) / np.where(det > 0, det, 1.0), 0.0)
    a = np.where(sw > 0, (sv - b * su) / np.maximum(sw, 1.0), 0.0)
    return a, b


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
