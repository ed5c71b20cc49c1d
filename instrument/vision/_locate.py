"""``locate_cross``: one camera image → the sub-pixel cross (method.md §2).

Pipeline: coarse stripes on a block-averaged copy (``_detect``) → for each stripe a narrow band of
full-resolution pixels following it (one gather, integers only) → IGCF on every cross-section of the
band at once (``_igcf``), the crossing zone left out → bisquare line fit (``_linefit``) →
intersection and angles (§2.4).
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from instrument.vision._detect import CoarseLine, find_stripes
from instrument.vision._igcf import SectionCentres, half_window_for_width, igcf_band, stripe_fwhm
from instrument.vision._linefit import LineFit, fit_line_bisquare
from instrument.vision._types import CrossMeasurement, CrossNotFound, StripeLine

BAND_HALF_WIDTH = 12  # px each side of the coarse line: holds the stripe, its window and plateau
MIN_SECTIONS = 30  # fewer usable cross-sections than this: the stripe is too short to fit
MIN_AMPLITUDE_SIGMAS = 6.0  # sections whose peak is weaker than this many noise σ are left out
DEFAULT_SATURATION = {np.dtype(np.uint8): 255, np.dtype(np.uint16): 65535}
MIN_SIDE = 16
EDGE_ROWS = np.r_[0:2, -2:0]  # band rows that sample the background (≥ 11 px from the line)
BACKGROUND_SPAN = 31  # sections averaged for the local background


class _Band(NamedTuple):
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


class _StripeFit(NamedTuple):
    line: LineFit
    points: np.ndarray  # (N, 2) x, y of the sections' centres
    saturated: int
    peak: float


def _check_image(img, saturation):
    if not isinstance(img, np.ndarray):
        raise TypeError(f"image must be a numpy array, got {type(img).__name__}")
    if img.dtype not in DEFAULT_SATURATION:
        raise TypeError(f"image must be uint8 or uint16 greyscale, got dtype {img.dtype}")
    if img.ndim != 2:
        raise ValueError(
            f"image must be 2-D (rows, cols) greyscale, got shape {img.shape}"
            + (" — convert colour images to one channel first" if img.ndim == 3 else "")
        )
    if min(img.shape) < MIN_SIDE:
        raise ValueError(
            f"image is too small to hold a cross: shape {img.shape}, need ≥ {MIN_SIDE} px a side"
        )
    full_scale = DEFAULT_SATURATION[img.dtype]
    if saturation is None:
        return full_scale
    if not (0 < float(saturation) <= full_scale):
        raise ValueError(f"saturation must be in (0, {full_scale}] for {img.dtype} images, got {saturation}")
    return float(saturation)


def _kind(vertical):
    return "near-vertical" if vertical else "near-horizontal"


def _extract_band(flat, shape, line: CoarseLine, other: CoarseLine, fallback_bg, min_sections) -> _Band:
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
            f"{_kind(line.vertical)} stripe too short to fit: {len(s)} cross-sections outside the "
            f"crossing zone (need ≥ {min_sections})"
        )
    base = np.rint(position).astype(np.intp) - BAND_HALF_WIDTH
    k = np.arange(2 * BAND_HALF_WIDTH + 1)
    step, stride = (1, cols) if line.vertical else (cols, 1)  # flat-index steps across / along
    if base.min() >= 0 and base.max() + 2 * BAND_HALF_WIDTH < across_len:
        valid = None  # the whole band lies in the frame (the usual case): no masks needed
        index = (base * step + s * stride)[None, :] + (k * step)[:, None]
    else:
        across = base[None, :] + k[:, None]
        valid = (across >= 0) & (across < across_len)
        index = np.clip(across, 0, across_len - 1) * step + (s * stride)[None, :]
    values = flat.take(index)
    background, noise = _local_background(values, valid, fallback_bg)
    return _Band(values, valid, s, base, background, noise, line.vertical)


def _local_background(values, valid, fallback_bg):
    """Background per section and noise σ, from the band's two outer rows on each side.

    The edge pixels are averaged over ``BACKGROUND_SPAN`` neighbouring sections (a running mean),
    so a smooth gradient of ambient light is followed while the estimate stays quiet.
    """
    edges = values[EDGE_ROWS].astype(np.float32)
    weight = np.ones(edges.shape, np.float32) if valid is None else valid[EDGE_ROWS].astype(np.float32)
    if weight.sum() < 16:  # band cut off by the frame on both sides: use the frame's figures
        return np.full(values.shape[1], fallback_bg), 0.5
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


def _fit_stripe(band: _Band, centres: SectionCentres, min_sections) -> _StripeFit:
    """Bisquare line through the IGCF centres of one stripe."""
    ok = centres.valid
    n_ok = int(ok.sum())
    if n_ok < min_sections:
        raise CrossNotFound(
            f"{_kind(band.vertical)} stripe too short to fit: {n_ok} usable cross-sections "
            f"(need ≥ {min_sections})"
        )
    centre = band.base[ok] + centres.center[ok]
    along = band.along[ok].astype(float)
    points = np.column_stack([centre, along] if band.vertical else [along, centre])
    fit = fit_line_bisquare(points, independent=1 if band.vertical else 0)
    peak = float((centres.peak + band.background)[ok].max())
    return _StripeFit(fit, points, int(centres.saturated.sum()), peak)


def _section_centres(bands, saturation, half_window) -> list[SectionCentres]:
    """IGCF of every section of both bands in one vectorised call (halves the per-call overhead)."""
    sizes = [b.values.shape[1] for b in bands]

    def per_section(figure):  # one value per stripe (or per section) → one per section
        return np.concatenate([np.broadcast_to(figure(b), (n,)) for b, n in zip(bands, sizes)])

    if half_window is None:  # each stripe's window from its own width
        half_window = per_section(
            lambda b: half_window_for_width(stripe_fwhm(b.values, b.background, saturation))
        )
    values = np.concatenate([b.values for b in bands], axis=1)
    valid = None
    if any(b.valid is not None for b in bands):
        valid = np.concatenate(
            [np.ones(b.values.shape, bool) if b.valid is None else b.valid for b in bands], axis=1
        )
    result = igcf_band(
        values,
        valid,
        per_section(lambda b: b.background),
        saturation,
        half_window,
        per_section(lambda b: MIN_AMPLITUDE_SIGMAS * b.noise),
    )
    split = np.cumsum(sizes)[:-1]
    return [SectionCentres(*parts) for parts in zip(*(np.split(field, split) for field in result))]


def _stripe_line(fit: _StripeFit, vertical: bool) -> StripeLine:
    line = fit.line
    used = line.weights > 0
    independent = fit.points[:, 1 if vertical else 0]
    mean = float(np.average(independent, weights=line.weights))
    dependent = line.intercept + line.slope * mean
    direction = np.array([line.slope, 1.0] if vertical else [1.0, line.slope]) / np.hypot(1.0, line.slope)
    point = np.array([dependent, mean] if vertical else [mean, dependent])
    return StripeLine(point, direction, int(used.sum()), line.residual_rms, fit.saturated)


def locate_cross(img, saturation=None, *, threshold=None, half_window=None, min_sections=MIN_SECTIONS):
    """Locate a cross-line laser's cross in one camera image to sub-pixel precision (method.md §2).

    Parameters
    ----------
    img : ndarray, 2-D, uint8 or uint16
        The frame, ``img[row, col]``; pixel (row r, col c) is centred at image point (x=c, y=r).
    saturation : float, optional
        The sensor's saturation level; default 255 for uint8 and 65535 for uint16 (give 1023 or
        4095 for 10- or 12-bit data in 16-bit words).
    threshold : None, float or "otsu", optional
        Binarisation level used to find the stripes: None = a set level of 15 % of the contrast
        above background (at least 6 noise σ), a number = that grey level, "otsu" = Otsu's method.
    half_window : int, optional
        IGCF half-window h (window 2h+1 px); default from the stripe width, h = 2…4.
    min_sections : int, optional
        Fewest usable cross-sections per stripe (default 30).

    Returns
    -------
    CrossMeasurement
        Centre (x, y) px, angle θ = (φh+φv)/2 rad (positive from +x toward +y), both stripe lines
        with quality figures, perpendicularity φv − φh rad, peak level.

    Raises
    ------
    TypeError
        ``img`` is not a uint8/uint16 numpy array.
    ValueError
        ``img`` is not 2-D or too small, or ``saturation`` is out of range.
    CrossNotFound
        No cross, only one stripe, more than one cross, or a stripe too short to fit; the message
        says which.
    """
    saturation = _check_image(img, saturation)
    detection = find_stripes(img, saturation, threshold)
    flat = np.ascontiguousarray(img).ravel()
    bands = [
        _extract_band(flat, img.shape, line, other, detection.background, min_sections)
        for line, other in (
            (detection.horizontal, detection.vertical),
            (detection.vertical, detection.horizontal),
        )
    ]
    h_fit, v_fit = (
        _fit_stripe(band, centres, min_sections)
        for band, centres in zip(bands, _section_centres(bands, saturation, half_window))
    )
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
    )
