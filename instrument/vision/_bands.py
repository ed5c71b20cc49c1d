"""From two coarse stripe lines to the sub-pixel cross (method.md §2.2–§2.4), shared by the full
search and the tracking path.

For each stripe a narrow band of full-resolution pixels following its coarse line (one gather,
integers only) → IGCF on every cross-section of both bands at once (``_igcf``), the crossing zone
left out → bisquare line fit (``_linefit``) → intersection and angles.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np

from instrument.vision._detect import CoarseLine
from instrument.vision._igcf import SectionCentres, half_window_for_width, igcf_band, stripe_fwhm
from instrument.vision._linefit import LineFit, bisquare_line
from instrument.vision._types import CrossMeasurement, CrossNotFound, StripeLine

BAND_HALF_WIDTH = 12  # px each side of the coarse line: holds the stripe, its window and plateau
MIN_AMPLITUDE_SIGMAS = 6.0  # sections whose peak is weaker than this many noise σ are left out
EDGE_ROWS = np.r_[0:2, -2:0]  # band rows that sample the background (≥ 11 px from the line)
BACKGROUND_SPAN = 31  # sections averaged for the local background
NOISE_STRIDE = 8  # every 8th section's edge pixels give the noise σ (plenty of samples)


class Band(NamedTuple):
    """Full-resolution pixels following one stripe: ``values[k, i]`` is pixel ``base[i] + k``
    across the stripe in section ``along[i]`` (a column of a horizontal stripe, a row of a
    vertical one)."""

    values: np.ndarray  # (2·BAND_HALF_WIDTH+1, N) image dtype
    valid: np.ndarray | None  # same shape, or None when every pixel lies in the frame
    along: np.ndarray  # (N,) section index
    base: np.ndarray  # (N,) first pixel of the band across the stripe
    background: np.ndarray  # (N,) local background per section
    noise: float
    vertical: bool


class StripeFit(NamedTuple):
    line: LineFit  # centre = intercept + slope·along
    along: np.ndarray  # (N,) section coordinate of the centres used
    saturated: int
    peak: float


def kind(vertical: bool) -> str:
    return "near-vertical" if vertical else "near-horizontal"


def extract_band(flat, shape, line: CoarseLine, other: CoarseLine, fallback_bg, min_sections) -> Band:
    """One gather of the band around ``line``, the crossing zone left out."""
    rows, cols = shape
    n_sections, across_len = (rows, cols) if line.vertical else (cols, rows)
    s = np.arange(n_sections)
    position = line.at(s)
    # leave out the crossing: sections where the other stripe passes within the band
    other_at = other.at(position)
    reach = BAND_HALF_WIDTH * (1.0 + abs(other.slope)) + BAND_HALF_WIDTH
    keep = np.abs(s - other_at) > reach
    keep &= (position > -BAND_HALF_WIDTH) & (position < across_len - 1 + BAND_HALF_WIDTH)
    s, position = s[keep], position[keep]
    if len(s) < min_sections:
        raise CrossNotFound(
            f"{kind(line.vertical)} stripe too short to fit: {len(s)} cross-sections outside the "
            f"crossing zone (need ≥ {min_sections})"
        )
    base = np.rint(position).astype(np.intp) - BAND_HALF_WIDTH
    k = np.arange(2 * BAND_HALF_WIDTH + 1)
    step, stride = (1, cols) if line.vertical else (cols, 1)  # flat-index steps across / along
    if base[0] >= 0 and base[-1] >= 0 and max(base[0], base[-1]) + 2 * BAND_HALF_WIDTH < across_len:
        valid = None  # the whole band lies in the frame (the usual case): no masks needed
        index = np.add.outer(k * step, base * step + s * stride)
    else:
        across = base[None, :] + k[:, None]
        valid = (across >= 0) & (across < across_len)
        index = np.clip(across, 0, across_len - 1) * step + (s * stride)[None, :]
    values = flat.take(index)
    background, noise = _local_background(values, valid, fallback_bg)
    return Band(values, valid, s, base, background, noise, line.vertical)


_EDGE_COUNTS: dict[int, np.ndarray] = {}


def _edge_counts(n: int) -> np.ndarray:
    """Edge pixels inside the running window of each of n sections (cached: the same n recur)."""
    counts = _EDGE_COUNTS.get(n)
    if counts is None:
        half = BACKGROUND_SPAN // 2
        i = np.arange(n)
        counts = (np.minimum(i + half, n - 1) - np.maximum(i - half, 0) + 1) * float(len(EDGE_ROWS))
        if len(_EDGE_COUNTS) > 64:  # a stream sees a handful of lengths; never grow without bound
            _EDGE_COUNTS.clear()
        _EDGE_COUNTS[n] = counts
    return counts


def _local_background(values, valid, fallback_bg):
    """Background per section and noise σ, from the band's two outer rows on each side.

    The edge pixels are averaged over ``BACKGROUND_SPAN`` neighbouring sections (a running mean),
    so a smooth gradient of ambient light is followed while the estimate stays quiet.
    """
    edges = values[EDGE_ROWS].astype(np.float32)
    n = values.shape[1]
    if valid is None:  # every edge pixel exists: the counts of the running sum are known
        total = cv2.boxFilter(
            edges.sum(axis=0)[None, :], -1, (BACKGROUND_SPAN, 1), normalize=False, borderType=cv2.BORDER_CONSTANT
        )[0]
        background = total / _edge_counts(n)
        sample = edges[:, ::NOISE_STRIDE] - background[::NOISE_STRIDE].astype(np.float32)
        noise = math.sqrt(float(np.einsum("ij,ij->", sample, sample)) / sample.size)
        return background, max(noise, 0.5)
    weight = valid[EDGE_ROWS].astype(np.float32)
    if weight.sum() < 16:  # band cut off by the frame on both sides: use the frame's figures
        return np.full(n, fallback_bg), 0.5
    # running sums of edge levels and of edge-pixel counts over BACKGROUND_SPAN sections at once
    sums = cv2.boxFilter(
        np.stack([(edges * weight).sum(axis=0), weight.sum(axis=0)]),
        -1,
        (BACKGROUND_SPAN, 1),
        normalize=False,
        borderType=cv2.BORDER_CONSTANT,
    )
    total, count = sums[0], sums[1]
    background = np.where(count > 0.5, total / np.maximum(count, 1.0), fallback_bg)
    residual = (edges - background[None, :].astype(np.float32)) * weight
    noise = float(np.sqrt((residual * residual).sum() / weight.sum()))
    return background, max(noise, 0.5)


def section_centres(bands, saturation, half_window) -> list[SectionCentres]:
    """IGCF of every section of all ``bands`` in one vectorised call (the per-call overhead is paid
    once, however many stripes — or frames — there are). ``saturation`` is one level, or one per band.
    """
    sizes = [b.values.shape[1] for b in bands]
    levels = list(saturation) if isinstance(saturation, (list, tuple)) else [saturation] * len(bands)

    def per_section(values):  # one value per band → one per section
        return np.repeat(np.asarray(values, dtype=float), sizes)

    if half_window is None:  # each stripe's window from its own width
        half_window = per_section(
            [half_window_for_width(stripe_fwhm(b.values, b.background, level)) for b, level in zip(bands, levels)]
        ).astype(np.intp)
    values = np.concatenate([b.values for b in bands], axis=1)
    valid = None
    if any(b.valid is not None for b in bands):
        valid = np.concatenate(
            [np.ones(b.values.shape, bool) if b.valid is None else b.valid for b in bands], axis=1
        )
    result = igcf_band(
        values,
        valid,
        np.concatenate([b.background for b in bands]),
        levels[0] if len(set(levels)) == 1 else per_section(levels),
        half_window,
        per_section([MIN_AMPLITUDE_SIGMAS * b.noise for b in bands]),
    )
    bounds = np.cumsum([0, *sizes])
    return [SectionCentres(*(field[lo:hi] for field in result)) for lo, hi in zip(bounds[:-1], bounds[1:])]


def fit_stripe(band: Band, centres: SectionCentres, min_sections) -> StripeFit:
    """Bisquare line through the IGCF centres of one stripe: centre = a + b·along."""
    ok = centres.valid
    n_ok = int(np.count_nonzero(ok))
    if n_ok < min_sections:
        raise CrossNotFound(
            f"{kind(band.vertical)} stripe too short to fit: {n_ok} usable cross-sections "
            f"(need ≥ {min_sections})"
        )
    centre = band.base[ok] + centres.center[ok]
    along = band.along[ok].astype(float)
    fit = bisquare_line(along, centre)
    peak = float((centres.peak + band.background)[ok].max())
    return StripeFit(fit, along, int(np.count_nonzero(centres.saturated)), peak)


def _stripe_line(fit: StripeFit, vertical: bool) -> StripeLine:
    line = fit.line
    used = int(np.count_nonzero(line.weights))
    mean = float(line.weights @ fit.along / line.weights.sum())
    dependent = line.intercept + line.slope * mean
    direction = np.array([line.slope, 1.0] if vertical else [1.0, line.slope]) / np.hypot(1.0, line.slope)
    point = np.array([dependent, mean] if vertical else [mean, dependent])
    return StripeLine(point, direction, used, line.residual_rms, fit.saturated)


class CrossJob(NamedTuple):
    """One frame's two coarse lines, ready for the fine stage."""

    flat: np.ndarray  # the C-contiguous frame, raveled
    shape: tuple[int, int]
    horizontal: CoarseLine
    vertical: CoarseLine
    fallback_bg: float
    saturation: float
    search: str = "full"


def measure_crosses(jobs, half_window, min_sections) -> list[CrossMeasurement | CrossNotFound]:
    """The sub-pixel crosses of several frames at once (one IGCF call for all their stripes).

    Each entry of the result is the frame's ``CrossMeasurement``, or the ``CrossNotFound`` it
    raised (returned, not raised, so that one bad frame does not cost the others their result).
    """
    results: dict[int, CrossMeasurement | CrossNotFound] = {}
    prepared = []  # (job number, job, [horizontal band, vertical band])
    for number, job in enumerate(jobs):
        try:
            bands = [
                extract_band(job.flat, job.shape, line, other, job.fallback_bg, min_sections)
                for line, other in ((job.horizontal, job.vertical), (job.vertical, job.horizontal))
            ]
        except CrossNotFound as exc:
            results[number] = exc
            continue
        prepared.append((number, job, bands))
    if prepared:
        bands = [band for _, _, pair in prepared for band in pair]
        levels = [job.saturation for _, job, _ in prepared for _ in range(2)]
        centres = section_centres(bands, levels, half_window)
        for k, (number, job, pair) in enumerate(prepared):
            try:
                h_fit, v_fit = (fit_stripe(pair[i], centres[2 * k + i], min_sections) for i in range(2))
            except CrossNotFound as exc:
                results[number] = exc
                continue
            results[number] = _cross(h_fit, v_fit, job.search)
    return [results[number] for number in range(len(jobs))]


def measure_cross(
    flat,
    shape,
    horizontal: CoarseLine,
    vertical: CoarseLine,
    fallback_bg: float,
    saturation: float,
    half_window,
    min_sections: int,
    search: str = "full",
) -> CrossMeasurement:
    """The sub-pixel cross of one frame from two coarse lines good to about a pixel.

    ``flat`` is the C-contiguous frame raveled; raises ``CrossNotFound`` when a stripe has too few
    usable sections.
    """
    job = CrossJob(flat, shape, horizontal, vertical, fallback_bg, saturation, search)
    (result,) = measure_crosses([job], half_window, min_sections)
    if isinstance(result, CrossNotFound):
        raise result
    return result


def _cross(h_fit: StripeFit, v_fit: StripeFit, search: str) -> CrossMeasurement:
    """Intersection and angles of the two fitted stripe lines (method.md §2.4)."""
    a_h, b_h = h_fit.line.intercept, h_fit.line.slope  # y = a_h + b_h·x
    a_v, b_v = v_fit.line.intercept, v_fit.line.slope  # x = a_v + b_v·y
    x = (a_v + b_v * a_h) / (1.0 - b_v * b_h)
    center = np.array([x, a_h + b_h * x])
    phi_h = float(np.arctan(b_h))  # atan2(dy, dx) with d = (1, b_h) toward +x
    phi_v = float(-np.arctan(b_v))  # atan2(−dx, dy) with d = (b_v, 1) toward +y
    return CrossMeasurement(
        center=center,
        angle=0.5 * (phi_h + phi_v),
        horizontal=_stripe_line(h_fit, vertical=False),
        vertical=_stripe_line(v_fit, vertical=True),
        perpendicularity=phi_v - phi_h,
        peak_level=max(h_fit.peak, v_fit.peak),
        search=search,
    )
