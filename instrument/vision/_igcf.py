"""Improved Gaussian curve fitting (IGCF) of stripe cross-sections, vectorised (method.md §2.2).

Each cross-section (a column of the band for the horizontal stripe, a row for the vertical one) is
handled at once for all sections with array operations — no Python loop per section:

1. coarse centre: the middle of the brightest run (from the first to the last pixel at the
   section's maximum: the saturated plateau, or the peak pixel);
2. saturation rule: if two or more neighbouring pixels are saturated, every saturated pixel of the
   section leaves the fit; a lone saturated pixel stays;
3. a window of 2·h+1 pixels around the coarse centre (h = 2…4, scaled with the stripe width),
   widened by the saturated plateau where the rule removed pixels;
4. background-subtracted ln I fitted with a parabola a0 + a1·t + a2·t², weighted by I²;
5. centre = coarse − a1/(2·a2); rejected when a2 ≥ 0, fewer than 3 pixels, vertex outside the
   window, run touching the profile's end, or peak below ``min_amplitude``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from instrument.vision._linefit import _median

MIN_HALF_WINDOW, MAX_HALF_WINDOW = 2, 4  # windows of 5…9 px (method.md §2.2)
FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))


class SectionCentres(NamedTuple):
    """Per-section IGCF result; arrays of length N (one entry per cross-section).

    Attributes
    ----------
    center : ndarray
        Sub-pixel centre in index units along the profile; NaN where ``valid`` is False.
    valid : ndarray of bool
        The section passed every rejection rule.
    saturated : ndarray of bool
        The saturation rule removed pixels from this section.
    peak : ndarray
        Highest level of the section above background.
    run_length : ndarray of int
        Length of the brightest run (pixels at the section maximum: the saturated plateau, or
        usually 1 on an unsaturated profile).
    """

    center: np.ndarray
    valid: np.ndarray
    saturated: np.ndarray
    peak: np.ndarray
    run_length: np.ndarray


def half_window_for_width(fwhm):
    """Half-window h (window 2h+1 = 5…9 px) for a stripe of full width at half maximum ``fwhm`` px.

    About ±2σ of a Gaussian carries all but a few per cent of the centre information under the I²
    weighting; ±2σ ≈ ±0.85·FWHM.
    """
    return int(np.clip(np.rint(0.85 * float(fwhm)), MIN_HALF_WINDOW, MAX_HALF_WINDOW))


def igcf_centers(
    profiles,
    *,
    axis=-1,
    background=0.0,
    saturation=None,
    half_window=None,
    valid=None,
    min_amplitude=0.0,
):
    """Sub-pixel centres of many stripe cross-sections at once (IGCF, method.md §2.2).

    Parameters
    ----------
    profiles : array_like, 2-D
        Grey levels; each 1-D slice along ``axis`` is one cross-section (profile index = pixel
        coordinate across the stripe).
    axis : int
        The axis running across the stripe (along each profile). The other axis enumerates sections.
    background : float or array_like
        Background level subtracted before the logarithm; a scalar or one value per section.
    saturation : float or None
        Sensor saturation level; None disables the saturation rule.
    half_window : int, array_like of int, or None
        h of the 2h+1-pixel fit window (one value, or one per section); None chooses it from the
        median width at half maximum of the unsaturated sections (:func:`stripe_fwhm`,
        :func:`half_window_for_width`).
    valid : array_like of bool or None
        Same shape as ``profiles``; False marks pixels that do not exist (outside the image).
    min_amplitude : float or array_like
        Sections whose peak above background is below this are rejected.

    Returns
    -------
    SectionCentres
        ``center`` is in index units along ``axis``.
    """
    band = np.asarray(profiles)
    if band.ndim != 2:
        raise ValueError(f"profiles must be 2-D, got shape {band.shape}")
    band = np.moveaxis(band, axis, 0)
    mask = None if valid is None else np.moveaxis(np.asarray(valid, dtype=bool), axis, 0)
    return igcf_band(band, mask, background, saturation, half_window, min_amplitude)


_POWERS: dict[int, np.ndarray] = {}


def _powers(h_max):
    """Rows 1, t, t², t³, t⁴ for t = −h_max … h_max+1 (cached: the same few windows recur)."""
    if h_max not in _POWERS:
        t = np.arange(-h_max, h_max + 2, dtype=np.float32)
        _POWERS[h_max] = np.stack([np.ones_like(t), t, t**2, t**3, t**4])
    return _POWERS[h_max]


def _brightest_runs(band):
    """Peak value, and middle and length of the run of pixels at the peak, per section (axis 0).

    The pixels equal to the section's maximum are counted, and their indices summed, by integer
    reductions across the rows — far cheaper than an argmax along the strided axis. For a
    contiguous run (a saturated plateau, or the single peak pixel) the mean index is the run's middle.
    """
    peak = band.max(axis=0)
    at_peak = band == peak[None, :]
    length = band.shape[0]
    count = at_peak.sum(axis=0, dtype=np.uint16)
    rows = _row_indices(length)
    index_sum = np.multiply(at_peak, rows, dtype=rows.dtype).sum(axis=0, dtype=np.uint32)
    count_f = count.astype(np.float32)
    return peak, index_sum / count_f, count_f


_ROWS: dict[int, np.ndarray] = {}


def _row_indices(length: int) -> np.ndarray:
    """0 … length−1 as a column, in the smallest unsigned type that holds them (cached)."""
    rows = _ROWS.get(length)
    if rows is None:
        rows = np.arange(length, dtype=np.uint8 if length <= 256 else np.uint32)[:, None]
        _ROWS[length] = rows
    return rows


def igcf_band(band, valid, background, saturation, half_window, min_amplitude):
    """:func:`igcf_centers` on a band laid out (profile length L, sections N) — the fast path.

    ``band`` is an integer (or float) array; ``valid`` a bool array of the same shape or None
    (every pixel exists). Element-wise work is done in float32 on the 2h+1-row window only; the
    moment sums and the 3×3 solution in float64.
    """
    length, n = band.shape
    cols = np.arange(n)
    bg = np.broadcast_to(np.asarray(background, dtype=float), (n,))
    if valid is not None:
        band = np.where(valid, band, 0)  # missing pixels can never be the brightest
    peak_raw, middle, run = _brightest_runs(band)
    amplitude = peak_raw.astype(float) - bg
    # coarse centre: the middle of the brightest run (the saturated plateau, or the peak pixel)
    coarse = np.floor(middle).astype(np.intp)
    half_step = (middle - coarse) > 0.25  # an even run: its middle lies between two pixels
    first = np.rint(middle - 0.5 * (run - 1)).astype(np.intp)
    last = np.rint(middle + 0.5 * (run - 1)).astype(np.intp)
    # the profile must continue on both sides of the run, or the true peak may lie off the band
    contained = (first > 0) & (last < length - 1)
    if valid is not None:
        contained &= valid[np.maximum(first - 1, 0), cols] & valid[np.minimum(last + 1, length - 1), cols]

    if saturation is not None:
        plateau = (peak_raw >= saturation) & (run >= 2)  # ≥ 2 neighbouring saturated pixels
        n_dropped = np.where(plateau, run, 0).astype(np.intp)
    else:
        plateau = np.zeros(n, dtype=bool)
        n_dropped = np.zeros(n, dtype=np.intp)

    if half_window is None:
        half_window = half_window_for_width(stripe_fwhm(band, bg, saturation))
    # widen the window over a removed plateau so both flanks keep h pixels
    h_sec = np.asarray(half_window, dtype=np.intp) + (n_dropped + 1) // 2
    h_max = int(min(h_sec.max(initial=MIN_HALF_WINDOW), (length - 1) // 2))
    h_sec = np.minimum(h_sec, h_max)

    # the window is symmetric about the run's middle: t = −h…h, or −h+1…h when the middle is at
    # +1/2 — an off-centre window would weigh one flank more, which biases clipped profiles
    t = np.arange(-h_max, h_max + 2)
    use = None  # window pixels that enter the fit; None = all so far (skips mask work)
    if coarse.min() - h_max < 0 or coarse.max() + h_max + 1 >= length:
        rows = coarse[None, :] + t[:, None]
        use = (rows >= 0) & (rows < length)
        flat_index = np.clip(rows, 0, length - 1) * n + cols[None, :]
    else:
        flat_index = (coarse * n + cols)[None, :] + (t * n)[:, None]
    values = band.ravel().take(flat_index)
    # keep t in [−h + s, h], s = 1 for a half-pixel middle, else 0
    tt = t[:, None]
    masks = [(tt >= (half_step - h_sec)[None, :]) & (tt <= h_sec[None, :])]
    if valid is not None:
        masks.append(valid.ravel().take(flat_index))
    if plateau.any():
        masks.append(~((values >= saturation) & plateau[None, :]))
    for mask in masks:
        use = mask if use is None else use & mask
    # normalised to the section's amplitude: the I² weights and logs stay O(1) for any bit depth
    inv_scale = (1.0 / np.where(amplitude > 0, amplitude, 1.0)).astype(np.float32)
    level = values.astype(np.float32)
    level -= bg.astype(np.float32)[None, :]
    level *= inv_scale[None, :]
    positive = level > 0
    use = positive if use is None else use & positive
    # weight = I² and weight·ln I side by side, so one matrix product gives all eight moment sums
    window_rows = level.shape[0]
    sums_input = np.empty((window_rows, 2 * n), np.float32)
    weight, weighted_log = sums_input[:, :n], sums_input[:, n:]
    np.copyto(level, 1.0, where=~use)  # ln 1 = 0 and the weight below is 0: unused pixels add nothing
    np.multiply(level, level, out=weight)
    weight *= use
    np.log(level, out=weighted_log)
    weighted_log *= weight

    sums = (_powers(h_max) @ sums_input).astype(float)
    s0, s1, s2, s3, s4 = sums[:, :n]
    z0, z1, z2 = sums[:3, n:]
    n_used = use.view(np.uint8).sum(axis=0, dtype=np.uint8)
    # Cramer's rule on the 3×3 normal equations; centre = −a1/(2·a2) needs only det1 and det2 (the
    # determinant itself is positive: a weighted Gram matrix of ≥ 3 distinct points)
    m2, m3, mz = s1 * s4 - s3 * s2, s1 * s3 - s2 * s2, s1 * z2 - z1 * s2  # shared minors
    det1 = s0 * (z1 * s4 - s3 * z2) - z0 * m2 + s2 * mz
    det2 = s0 * (s2 * z2 - z1 * s3) - s1 * mz + z0 * m3
    fittable = (n_used >= 3) & (det2 < 0)  # det2/det = a2 < 0: a peak, not a dip
    offset = det1 / (-2.0 * np.where(fittable, det2, -1.0))
    ok = contained & fittable & (np.abs(offset) <= h_sec + 0.5)
    ok &= amplitude >= np.maximum(min_amplitude, np.finfo(float).tiny)
    center = np.where(ok, coarse + offset, np.nan)
    return SectionCentres(center, ok, plateau & ok, amplitude, run.astype(np.intp))


def stripe_fwhm(band, background, saturation=None, stride=8):
    """Width at half maximum of a stripe, px along the profiles: the median over every
    ``stride``-th section of a band laid out (profile length L, sections N), saturated sections
    left out. Cheap: a coarse figure to size the fit windows.
    """
    sub = band[:, ::stride]
    bg = np.broadcast_to(np.asarray(background, dtype=float), (band.shape[1],))[::stride]
    peak = sub.max(axis=0)
    half = 0.5 * (bg + peak)
    if np.issubdtype(band.dtype, np.integer):  # x ≥ h ⟺ x ≥ ⌈h⌉ for integers: compare natively
        half = np.ceil(half).astype(band.dtype)
    counts = (sub >= half[None, :]).sum(axis=0)
    usable = peak > bg
    if saturation is not None:
        usable &= peak < saturation
    if not usable.any():
        return FWHM_PER_SIGMA * 2.0  # nothing to measure: assume σ = 2 px
    counts = counts[usable]
    return _median(counts.astype(float))
