"""From two coarse stripe lines to the sub-pixel cross (method.md §2.2–§2.4), shared by the full
search and the tracking path.

All the stripes of a call (two per frame, six for a trigger of three cameras) go through each
step together, so every numpy operation is paid once per call, not once per stripe:

1. **bands**: for each stripe, the ``2·BAND_HALF_WIDTH + 1`` full-resolution pixels across its
   coarse line in every cross-section (a column of a horizontal stripe, a row of a vertical one),
   the crossing zone left out — one fancy-index read per stripe through a strided view of the
   frame, into one (sections, across) array, turned once into (across, sections);
2. **local background** per section (running mean of the outer rows within each stripe), the
   noise and the stripe width per stripe;
3. **IGCF** of every section of every stripe in one call (``_igcf``);
4. **bisquare lines** through each stripe's centres (``_linefit``), one IRLS per stripe;
   intersection and angles per frame.

The large arrays live in a :class:`VisionWorkspace` (see there for why).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np

from instrument.vision._detect import CoarseLine
from instrument.vision._igcf import FWHM_PER_SIGMA, MAX_HALF_WINDOW, MIN_HALF_WINDOW, SectionCentres
from instrument.vision._linefit import LineFit
from instrument.vision._strided import across_view
from instrument.vision._types import CrossMeasurement, CrossNotFound, StripeLine
from instrument.vision._workspace import VisionWorkspace

BAND_HALF_WIDTH = 12  # px each side of the coarse line: holds the stripe, its window and plateau
BAND_WIDTH = 2 * BAND_HALF_WIDTH + 1
MIN_AMPLITUDE_SIGMAS = 6.0  # sections whose peak is weaker than this many noise σ are left out
EDGE_ROWS = np.r_[0:2, BAND_WIDTH - 2 : BAND_WIDTH]  # band rows that sample the background (≥ 11 px from the line)
BACKGROUND_SPAN = 31  # sections averaged for the local background
SAMPLE_STRIDE = 8  # every 8th section's pixels give the noise σ and the stripe width (plenty of samples)
MIN_EDGE_PIXELS = 16  # a band with fewer background pixels in the frame uses the frame's figures


def kind(vertical: bool) -> str:
    return "near-vertical" if vertical else "near-horizontal"


class BandPlan(NamedTuple):
    """Where one stripe's band lies: ``base[i] + k`` (k = 0 … BAND_WIDTH−1) across the stripe in
    section ``along[i]``."""

    along: np.ndarray  # (N,) section index (column of a horizontal stripe, row of a vertical one)
    position: np.ndarray  # (N,) the coarse line across the stripe in each section, px
    base: np.ndarray  # (N,) first pixel of the band across the stripe
    inside: bool  # every pixel of the band lies in the frame (the usual case)
    vertical: bool


def plan_band(shape, line: CoarseLine, other: CoarseLine, min_sections) -> BandPlan:
    """The sections of the band around ``line``, the crossing zone left out."""
    rows, cols = shape
    n_sections, across_len = (rows, cols) if line.vertical else (cols, rows)
    s = _kept_sections(n_sections, across_len, line, other)
    if len(s) < min_sections:
        raise CrossNotFound(
            f"{kind(line.vertical)} stripe too short to fit: {len(s)} cross-sections outside the "
            f"crossing zone (need ≥ {min_sections})"
        )
    position = line.intercept + line.slope * s.astype(float)
    base = np.rint(position).astype(np.intp) - BAND_HALF_WIDTH
    low, high = min(base[0], base[-1]), max(base[0], base[-1])  # base is monotonic along the stripe
    return BandPlan(s, position, base, bool(low >= 0 and high + BAND_WIDTH <= across_len), line.vertical)


def _kept_sections(n_sections: int, across_len: int, line: CoarseLine, other: CoarseLine) -> np.ndarray:
    """The sections that enter the band, in order: with the line inside the frame (to within the
    band) and outside the crossing zone (the other stripe passes farther than the band's reach).

    Both conditions are linear in the section index s: the first holds on one run of sections,
    the second outside one run. Each run's ends are found from the analytic crossing point by
    testing the condition exactly as the elementwise float64 test of :func:`_keep_mask` would
    (Python floats are IEEE doubles) on the few sections next to it; where that does not settle
    within a few sections (no run, a run at the frame's end), the elementwise test decides.
    """
    reach = BAND_HALF_WIDTH * (1.0 + abs(other.slope)) + BAND_HALF_WIDTH
    far_edge = across_len - 1 + BAND_HALF_WIDTH
    a, b = line.intercept, line.slope
    c = 1.0 - other.slope * b
    if b == 0 or c == 0:
        return _keep_mask_sections(n_sections, across_len, line, other)

    def in_frame(s: int) -> bool:
        return -BAND_HALF_WIDTH < a + b * s < far_edge

    def out_of_frame(s: int) -> bool:
        return not in_frame(s)

    def in_crossing(s: int) -> bool:
        return not abs(s - (other.intercept + other.slope * (a + b * s))) > reach

    def out_of_crossing(s: int) -> bool:
        return not in_crossing(s)

    def edge(test, guess: float) -> int | None:
        """The s where ``test`` turns from False to True, within a few sections of ``guess``."""
        if not abs(guess) < 1e15:  # NaN, infinite or absurd lines: let the elementwise test decide
            return None
        if not -4 < guess < n_sections + 4:  # far off the sections: rounding cannot move it among them
            return math.floor(guess)
        s = math.floor(guess) + 1  # the turn is usually between floor(guess) and floor(guess) + 1
        for _ in range(6):
            before, here = test(s - 1), test(s)
            if not before and here:
                return s
            s += -1 if before else 1
        return None

    low_edge, high_edge = (-BAND_HALF_WIDTH - a) / b, (far_edge - a) / b
    enter, leave = edge(in_frame, min(low_edge, high_edge)), edge(out_of_frame, max(low_edge, high_edge))
    centre = (other.intercept + other.slope * a) / c
    zone_first, zone_stop = edge(in_crossing, centre - reach / abs(c)), edge(out_of_crossing, centre + reach / abs(c))
    if None in (enter, leave, zone_first, zone_stop):
        return _keep_mask_sections(n_sections, across_len, line, other)
    assert enter is not None and leave is not None and zone_first is not None and zone_stop is not None
    first, stop = max(enter, 0), min(leave, n_sections)
    if first >= stop:
        return np.arange(0)
    zone_first, zone_stop = min(max(zone_first, first), stop), min(max(zone_stop, first), stop)
    return np.concatenate([np.arange(first, zone_first), np.arange(max(zone_stop, zone_first), stop)])


def _keep_mask_sections(n_sections: int, across_len: int, line: CoarseLine, other: CoarseLine) -> np.ndarray:
    """:func:`_kept_sections` by testing every section (the general case)."""
    s = np.arange(n_sections)
    position = line.at(s)
    reach = BAND_HALF_WIDTH * (1.0 + abs(other.slope)) + BAND_HALF_WIDTH
    keep = np.abs(s - other.at(position)) > reach
    keep &= (position > -BAND_HALF_WIDTH) & (position < across_len - 1 + BAND_HALF_WIDTH)
    return s[keep]


def _gather(flat, shape, plan: BandPlan, out, valid_out) -> None:
    """Write the band's pixels into ``out`` (sections, BAND_WIDTH); ``valid_out`` marks pixels in
    the frame (only for a band that leaves it; off-frame pixels read the nearest edge pixel)."""
    rows, cols = shape
    across_len = cols if plan.vertical else rows
    step, stride = (1, cols) if plan.vertical else (cols, 1)  # flat-index steps across / along
    first = plan.along * stride
    if plan.inside:
        out[...] = across_view(flat, BAND_WIDTH, step)[first + plan.base * step]
        return
    across = plan.base[:, None] + np.arange(BAND_WIDTH)[None, :]
    valid_out[...] = (across >= 0) & (across < across_len)
    out[...] = flat.take(np.clip(across, 0, across_len - 1) * step + first[:, None])


class Bands(NamedTuple):
    """All stripes' bands side by side: section ``i`` of stripe ``j`` is column ``starts[j] + i``."""

    values: np.ndarray  # (BAND_WIDTH, N) workspace array, image dtype
    by_section: np.ndarray  # (N, BAND_WIDTH) the same pixels, one section per row (workspace array)
    valid: np.ndarray | None  # same shape (False: off the frame), or None when all pixels exist
    starts: np.ndarray  # (stripes + 1,) column bounds
    background: np.ndarray  # (N,) local background per section
    noise: np.ndarray  # (stripes,) noise σ per stripe
    segments: Segments  # the layout's index arrays


class Segments(NamedTuple):
    """Index arrays that depend only on how many sections each stripe has (cached per layout)."""

    starts: np.ndarray  # (stripes + 1,) first section of each stripe, and the total
    window_low: np.ndarray  # (N,) first section of each section's running-mean window (same stripe)
    window_end: np.ndarray  # (N,) one past its last
    edge_count: np.ndarray  # (N,) edge pixels in that window when all exist
    sampled: np.ndarray  # every SAMPLE_STRIDE-th section of each stripe
    sample_starts: np.ndarray  # (stripes + 1,) where each stripe's samples start in ``sampled``
    sample_counts: np.ndarray  # (stripes,) samples per stripe
    sample_stripe: np.ndarray  # (samples,) the stripe of each sample


def segments(ws: VisionWorkspace, sizes: tuple[int, ...]) -> Segments:
    """Per section: the first and last section of its running-mean window within its own stripe;
    and the columns sampled for noise and width (every SAMPLE_STRIDE-th of each stripe)."""

    def make():
        starts = np.concatenate([[0], np.cumsum(sizes)])
        stripe_start = np.repeat(starts[:-1], sizes)
        stripe_last = np.repeat(starts[1:] - 1, sizes)
        i = np.arange(starts[-1])
        half = BACKGROUND_SPAN // 2
        low, high = np.maximum(i - half, stripe_start), np.minimum(i + half, stripe_last)
        sampled = np.concatenate([np.arange(lo, hi, SAMPLE_STRIDE) for lo, hi in zip(starts[:-1], starts[1:])])
        sample_counts = np.array([-(-n // SAMPLE_STRIDE) for n in sizes])
        sample_starts = np.concatenate([[0], np.cumsum(sample_counts)])
        return Segments(starts, low, high + 1, (high + 1 - low) * float(len(EDGE_ROWS)), sampled, sample_starts,
                        sample_counts, np.repeat(np.arange(len(sizes)), sample_counts))

    return ws.cached(("segments", sizes), make)


def extract_bands(jobs_plans, ws: VisionWorkspace, fallback_bgs) -> Bands:
    """Gather every planned band into one array and measure each stripe's background and noise.

    ``jobs_plans`` is a list of (flat frame, shape, BandPlan); ``fallback_bgs`` one frame
    background per band (used where a band has too few background pixels in the frame).
    """
    sizes = tuple(len(plan.along) for _, _, plan in jobs_plans)
    layout = segments(ws, sizes)
    starts, window_low, window_end, edge_count, sampled, sample_starts = layout[:6]
    n = int(starts[-1])
    dtype = np.result_type(*(flat.dtype for flat, _, _ in jobs_plans))
    by_section = ws.array("bands.by_section", (n, BAND_WIDTH), dtype)
    all_inside = all(plan.inside for _, _, plan in jobs_plans)
    valid_by_section = np.ones((n if not all_inside else 0, BAND_WIDTH), bool)
    for (flat, shape, plan), lo, hi in zip(jobs_plans, starts[:-1], starts[1:]):
        _gather(flat, shape, plan, by_section[lo:hi], None if plan.inside else valid_by_section[lo:hi])
    values = ws.array("bands.values", (BAND_WIDTH, n), dtype)
    if cv2.transpose(by_section, values) is not values:  # a dtype OpenCV does not take in place
        values[...] = by_section.T
    valid = None if all_inside else np.ascontiguousarray(valid_by_section.T)

    # background: running mean of the edge pixels over BACKGROUND_SPAN sections of the same stripe,
    # so a smooth gradient of ambient light is followed while the estimate stays quiet
    edges = values[EDGE_ROWS]
    edge_weight = None if valid is None else valid[EDGE_ROWS]
    edge_sum = np.add.reduce(edges if edge_weight is None else edges * edge_weight, axis=0, dtype=np.int64)
    running = np.zeros(n + 1, np.int64)
    edge_sum.cumsum(out=running[1:])
    total = running[window_end] - running[window_low]
    if edge_weight is None:
        background = total / edge_count
    else:
        running_count = np.zeros(n + 1, np.int64)
        np.cumsum(edge_weight.sum(axis=0), out=running_count[1:])
        count = (running_count[window_end] - running_count[window_low]).astype(float)
        background = np.where(count > 0.5, total / np.maximum(count, 1.0), np.repeat(fallback_bgs, sizes))
    # noise σ per stripe from the sampled sections' edge pixels
    residual = by_section[sampled][:, EDGE_ROWS].T - background[sampled].astype(np.float32)
    squares = residual * residual
    if edge_weight is None:
        square_sum = np.add.reduceat(np.add.reduce(squares, axis=0), sample_starts[:-1])
        pixels = layout.sample_counts * float(len(EDGE_ROWS))
    else:
        weight = edge_weight[:, sampled]
        square_sum = np.add.reduceat((squares * weight).sum(axis=0), sample_starts[:-1])
        pixels = np.add.reduceat(weight.sum(axis=0), sample_starts[:-1]).astype(float)
    noise = np.maximum(np.sqrt(square_sum / np.maximum(pixels, 1.0)), 0.5)
    if edge_weight is not None:  # bands cut off by the frame on both sides: use the frame's figures
        in_frame = np.add.reduceat(edge_weight.sum(axis=0), starts[:-1])
        for j in np.flatnonzero(in_frame < MIN_EDGE_PIXELS):
            background[starts[j] : starts[j + 1]] = fallback_bgs[j]
            noise[j] = 0.5
    return Bands(values, by_section, valid, starts, background, noise, layout)


def half_windows(bands: Bands, levels, ws: VisionWorkspace) -> np.ndarray:
    """IGCF half-window per stripe from its width at half maximum (``igcf.half_window_for_width``):
    the median over every SAMPLE_STRIDE-th section, saturated sections left out."""
    layout = bands.segments
    sampled, n_stripes = layout.sampled, len(layout.sample_counts)
    sub = cv2.transpose(bands.by_section[sampled])  # (BAND_WIDTH, samples): whole rows read, not columns
    background = bands.background[sampled]
    peak = np.maximum.reduce(sub, axis=0)
    half = np.ceil(0.5 * (background + peak)).astype(sub.dtype)  # x ≥ h ⟺ x ≥ ⌈h⌉ for integers
    widths = np.add.reduce(sub >= half[None, :], axis=0)
    stripe = layout.sample_stripe
    usable = (peak > background) & (peak < levels[stripe])
    # median width per stripe from a histogram of the (small, integer) widths
    bins = BAND_WIDTH + 1
    histogram = np.bincount(stripe[usable] * bins + widths[usable], minlength=n_stripes * bins)
    cumulative = histogram.reshape(n_stripes, bins).cumsum(axis=1)
    count = cumulative[:, -1]

    def order_statistic(k):  # the k-th smallest width of each stripe (0-based)
        return (cumulative > k[:, None]).argmax(axis=1)

    middle = count // 2
    fwhm = np.where(count % 2 == 1, order_statistic(middle), 0.5 * (order_statistic(np.maximum(middle - 1, 0))
                                                                     + order_statistic(middle)))
    fwhm = np.where(count > 0, fwhm, FWHM_PER_SIGMA * 2.0)  # nothing to measure: assume σ = 2 px
    return np.minimum(np.maximum(np.rint(0.85 * fwhm), MIN_HALF_WINDOW), MAX_HALF_WINDOW).astype(np.intp)


class StripeFit(NamedTuple):
    """A stripe's bisquare line through its usable centres, with what the cross reports of it."""

    line: LineFit  # centre = intercept + slope·along
    along: np.ndarray  # (N,) section coordinate of the centres used
    saturated: int
    peak: float


def _stripe_line(fit: StripeFit, vertical: bool) -> StripeLine:
    line = fit.line
    used = int(np.add.reduce(line.weights != 0))
    mean = float(line.weights @ fit.along / np.add.reduce(line.weights))
    dependent = line.intercept + line.slope * mean
    norm = math.hypot(1.0, line.slope)
    direction = np.array([line.slope / norm, 1.0 / norm] if vertical else [1.0 / norm, line.slope / norm])
    point = np.array([dependent, mean] if vertical else [mean, dependent])
    return StripeLine(point, direction, used, line.residual_rms, fit.saturated)


class CrossJob(NamedTuple):
    """One frame's two coarse lines, ready for the fine stage."""

    flat: np.ndarray  # the C-contiguous frame, raveled
    shape: tuple[int, int]
    horizontal: CoarseLine
    vertical: CoarseLine
    fallback_bg: float  # background where a band has too few pixels in the frame (NaN: none known)
    saturation: float
    search: str = "full"  # "tracked": the lines are the previous frame's, to be checked (``_track``)
    search_px: int = 0  # tracked: how far from its prior line a stripe is looked for


def usable_centres(plans: list[BandPlan], centres: SectionCentres, bands: Bands):
    """Per stripe: (along, centre, saturated sections, peak level) of its usable IGCF centres —
    all stripes' selected at once (one index, a few gathers), then cut per stripe."""
    starts = bands.starts[:-1]
    ok = centres.valid
    used = ok.nonzero()[0]
    bounds = np.concatenate([[0], np.add.reduceat(ok, starts).cumsum()])
    along = np.concatenate([plan.along for plan in plans]).take(used).astype(float)
    centre = np.concatenate([plan.base for plan in plans]).take(used) + centres.center.take(used)
    peaks = np.maximum.reduceat(np.where(ok, centres.peak + bands.background, -np.inf), starts)
    saturated = np.add.reduceat(centres.saturated, starts)
    return [(along[lo:hi], centre[lo:hi], int(saturated[j]), float(peaks[j]))
            for j, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:]))]


def too_short(plan: BandPlan, n_usable: int, min_sections: int) -> CrossNotFound | None:
    """The error for a stripe with fewer usable sections than ``min_sections``, else None."""
    if n_usable >= min_sections:
        return None
    return CrossNotFound(
        f"{kind(plan.vertical)} stripe too short to fit: {n_usable} usable cross-sections (need ≥ {min_sections})"
    )


def cross(h_fit: StripeFit, v_fit: StripeFit, search: str) -> CrossMeasurement:
    """Intersection and angles of the two fitted stripe lines (method.md §2.4)."""
    a_h, b_h = h_fit.line.intercept, h_fit.line.slope  # y = a_h + b_h·x
    a_v, b_v = v_fit.line.intercept, v_fit.line.slope  # x = a_v + b_v·y
    x = (a_v + b_v * a_h) / (1.0 - b_v * b_h)
    center = np.array([x, a_h + b_h * x])
    phi_h = math.atan(b_h)  # atan2(dy, dx) with d = (1, b_h) toward +x
    phi_v = -math.atan(b_v)  # atan2(−dx, dy) with d = (b_v, 1) toward +y
    return CrossMeasurement(
        center=center,
        angle=0.5 * (phi_h + phi_v),
        horizontal=_stripe_line(h_fit, vertical=False),
        vertical=_stripe_line(v_fit, vertical=True),
        perpendicularity=phi_v - phi_h,
        peak_level=max(h_fit.peak, v_fit.peak),
        search=search,
    )
