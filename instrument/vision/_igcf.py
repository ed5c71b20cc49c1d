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

import cv2
import numpy as np

from instrument.vision._linefit import _median
from instrument.vision._strided import across_view
from instrument.vision._workspace import VisionWorkspace

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
    """Rows 1, t, t², t³, t⁴ for t = −h_max … h_max (cached: the same few windows recur)."""
    if h_max not in _POWERS:
        t = np.arange(-h_max, h_max + 1, dtype=np.float32)
        _POWERS[h_max] = np.stack([np.ones_like(t), t, t**2, t**3, t**4])
    return _POWERS[h_max]


def _brightest_runs(band, workspace):
    """Peak value, and middle and length of the run of pixels at the peak, per section (axis 0).

    The pixels equal to the section's maximum are counted, and their indices summed, by integer
    reductions across the rows — far cheaper than an argmax along the strided axis. For a
    contiguous run (a saturated plateau, or the single peak pixel) the mean index is the run's middle.
    """
    length, n = band.shape
    peak = np.maximum.reduce(band, axis=0)
    at_peak = np.equal(band, peak[None, :], out=workspace.array("igcf.at_peak", band.shape, bool))
    small = length <= 255  # counts and indices fit one byte, index sums two: the cheapest reductions
    count = np.add.reduce(at_peak, axis=0, dtype=np.uint8 if small else np.uint32)
    rows = _row_indices(length)
    indices = np.multiply(at_peak, rows, out=workspace.array("igcf.indices", band.shape, rows.dtype))
    index_sum = np.add.reduce(indices, axis=0, dtype=np.uint16 if length <= 362 else np.uint32)
    count_f = count.astype(np.float32)  # small integers and their ratios: float32 is exact enough
    return peak, index_sum / count_f, count_f


_ROWS: dict[int, np.ndarray] = {}


def _row_indices(length: int) -> np.ndarray:
    """0 … length−1 as a column, in the smallest unsigned type that holds them (cached)."""
    rows = _ROWS.get(length)
    if rows is None:
        rows = np.arange(length, dtype=np.uint8 if length <= 256 else np.uint32)[:, None]
        _ROWS[length] = rows
    return rows


TINY = np.finfo(float).tiny  # a peak must stand above the background, however little
LOG_FLOOR = np.float32(1e-10)  # pixels left out of a fit sit here: weight 1e-20, weight·ln ≈ −2e-19 (nil)


class BrightestRuns(NamedTuple):
    """Per section of a band: the (masked) band they were found in, the peak value, the middle of
    the run of pixels at the peak and its length (see :func:`brightest_runs`)."""

    band: np.ndarray
    peak: np.ndarray
    middle: np.ndarray
    run: np.ndarray


def brightest_runs(band, valid, workspace) -> BrightestRuns:
    """:func:`_brightest_runs` of a band whose off-frame pixels (``valid`` False) read as 0."""
    if valid is not None:
        band = np.where(valid, band, 0)  # missing pixels can never be the brightest
    return BrightestRuns(band, *_brightest_runs(band, workspace))


def igcf_band(band, valid, background, saturation, half_window, min_amplitude, workspace=None, runs=None,
              by_section=None):
    """:func:`igcf_centers` on a band laid out (profile length L, sections N) — the fast path.

    ``band`` is an integer (or float) array; ``valid`` a bool array of the same shape or None
    (every pixel exists); ``workspace`` a :class:`VisionWorkspace` for the large temporaries (a
    fresh one if None); ``runs`` the band's :func:`brightest_runs` if already known; ``by_section``
    the band's transpose (N, L) C-contiguous, if at hand (the windows are then read from its rows,
    which is cheaper than gathering from the band's columns). Element-wise
    work is done in float32 on the 2h+1-row window only, the moment sums and the 3×3 solution too
    (the weights are normalised to the section's peak, so the sums are O(1–100) and the solution's
    rounding, ~1e-7 of the offset, is far below the centre's noise).
    """
    ws = VisionWorkspace() if workspace is None else workspace
    length, n = band.shape
    if isinstance(background, np.ndarray) and background.shape == (n,) and background.dtype == float:
        bg = background  # the usual case; np.broadcast_to is slow to call
    else:
        bg = np.broadcast_to(np.asarray(background, dtype=float), (n,))
    band, peak_raw, middle, run = brightest_runs(band, valid, ws) if runs is None else runs
    amplitude = peak_raw - bg
    # coarse centre: the middle of the brightest run (the saturated plateau, or the peak pixel)
    coarse = middle.astype(np.intp)  # floor: middle ≥ 0
    half_step = (middle - np.floor(middle)) > 0.25  # an even run: its middle lies between two pixels
    half_run = 0.5 * (run - 1)
    first = np.rint(middle - half_run)
    last = np.rint(middle + half_run)
    # the profile must continue on both sides of the run, or the true peak may lie off the band
    contained = (first > 0) & (last < length - 1)
    if valid is not None:
        first_i, last_i, cols = first.astype(np.intp), last.astype(np.intp), np.arange(n)
        contained &= valid[np.maximum(first_i - 1, 0), cols] & valid[np.minimum(last_i + 1, length - 1), cols]

    plateau = None
    h_sec = (half_window if getattr(half_window, "shape", None) == (n,)
             else np.broadcast_to(np.asarray(half_window if half_window is not None else 0, dtype=np.intp), (n,)))
    if saturation is not None:
        plateau = (peak_raw >= saturation) & (run >= 2)  # ≥ 2 neighbouring saturated pixels
        if np.logical_or.reduce(plateau):
            # widen the window over a removed plateau so both flanks keep h pixels
            h_sec = h_sec + (np.where(plateau, run, 0).astype(np.intp) + 1) // 2
        else:
            plateau = None
    if half_window is None:
        h_sec = h_sec + half_window_for_width(stripe_fwhm(band, bg, saturation))
    h_max = int(min(np.maximum.reduce(h_sec, initial=MIN_HALF_WINDOW), (length - 1) // 2))
    h_sec = np.minimum(h_sec, h_max)
    h_min = int(np.minimum.reduce(h_sec, initial=h_max))

    # normalised to the section's amplitude: the I² weights and logs stay O(1) for any bit depth
    inv_scale = (1.0 / np.where(amplitude > 0, amplitude, 1.0)).astype(np.float32)
    window = _Window(h_max, h_min, h_sec, half_step, bg.astype(np.float32), inv_scale, plateau, saturation)
    # a window cut by the profile's ends needs masks; such sections are few (a run at the band's
    # edge: noise, a hot pixel), so all sections are summed with their window moved inside the profile
    # and those few are summed again on their own with the masks
    near_end = (coarse < h_max) | (coarse >= length - h_max)
    rows = None if valid is not None else by_section
    if not np.logical_or.reduce(near_end):
        sums, n_used = _window_sums(band, valid, coarse, window, ws, None, rows)
    else:
        sums, n_used = _window_sums(band, valid, np.clip(coarse, h_max, length - 1 - h_max), window, ws, None, rows)
        redo = np.flatnonzero(near_end)
        redone, n_used[redo] = _window_sums(
            np.ascontiguousarray(band[:, redo]), None if valid is None else np.ascontiguousarray(valid[:, redo]),
            coarse[redo], window.subset(redo), VisionWorkspace(), length, None,
        )
        for row, value in zip(sums, redone):
            row[redo] = value
    s0, s1, s2, s3, s4, z0, z1, z2 = sums
    # the 3×3 normal equations with a0 eliminated by the first one (each row times s0):
    # A·a1 + B·a2 = P, B·a1 + C·a2 = Q; centre = −a1/(2·a2) needs only the two numerators of
    # Cramer's rule (the determinant A·C − B² is positive: a weighted Gram matrix of ≥ 3 points)
    a, b, c = s0 * s2 - s1 * s1, s0 * s3 - s1 * s2, s0 * s4 - s2 * s2
    p, q = s0 * z1 - s1 * z0, s0 * z2 - s2 * z0
    a1 = p * c - b * q  # a1 and a2 times the positive determinant A·C − B² (= s0 × that of the 3×3)
    a2 = a * q - b * p
    fittable = (n_used >= 3) & (a2 < 0)  # a2 < 0: a peak, not a dip
    offset = a1 / (-2.0 * np.where(fittable, a2, -1.0))
    ok = contained & fittable & (np.abs(offset) <= h_sec + 0.5)
    ok &= amplitude >= np.maximum(min_amplitude, TINY)
    center = np.where(ok, coarse + offset, np.nan)
    saturated = np.zeros(n, bool) if plateau is None else plateau & ok
    return SectionCentres(center, ok, saturated, amplitude, run.astype(np.intp))


class _Window(NamedTuple):
    """What decides which pixels of each section's window enter the IGCF fit."""

    h_max: int  # the window rows are t = −h_max … h_max around each section's coarse centre
    h_min: int
    h_sec: np.ndarray  # (N,) each section's own half-window (≤ h_max)
    half_step: np.ndarray  # (N,) the run's middle lies half a pixel past the coarse centre
    background: np.ndarray  # (N,) float32
    inv_scale: np.ndarray  # (N,) float32, 1 / amplitude
    plateau: np.ndarray | None  # (N,) the saturated plateau leaves the fit; None: no section has one
    saturation: float | None

    def subset(self, columns):
        return self._replace(
            h_sec=self.h_sec[columns], half_step=self.half_step[columns], background=self.background[columns],
            inv_scale=self.inv_scale[columns], plateau=None if self.plateau is None else self.plateau[columns],
        )


def _window_sums(band, valid, coarse, window: _Window, ws, profile_length, by_section):
    """Moment sums (8 rows of N, float32) — Σw·tᵖ for p = 0…4 and Σw·ln I·tᵖ for p = 0…2, w = I² — and the
    pixels used per section, over each section's window around ``coarse``.

    ``profile_length`` None: every window lies inside the profile; else the rows off it are masked.
    ``by_section``: the band transposed (N, L), to read each window as a run of one of its rows.
    """
    length, n = band.shape
    t = np.arange(-window.h_max, window.h_max + 1)
    rows_shape = (len(t), n)
    values = ws.array("igcf.values", rows_shape, band.dtype)
    outside = index = None
    if profile_length is None and by_section is not None:
        first = np.arange(0, n * length, length) + (coarse - window.h_max)
        if cv2.transpose(across_view(by_section.ravel(), len(t), 1)[first], values) is not values:
            values[...] = across_view(by_section.ravel(), len(t), 1)[first].T
    else:
        index = ws.array("igcf.index", rows_shape, np.intp)
        if profile_length is None:
            np.add((coarse * n + np.arange(n))[None, :], (t * n)[:, None], out=index)
        else:
            rows = coarse[None, :] + t[:, None]
            outside = (rows < 0) | (rows >= profile_length)
            np.add(np.clip(rows, 0, profile_length - 1) * n, np.arange(n)[None, :], out=index)
        band.ravel().take(index, out=values, mode="clip")
    level = np.subtract(values, window.background[None, :], out=ws.array("igcf.level", rows_shape, np.float32),
                        dtype=np.float32)
    level *= window.inv_scale[None, :]
    # pixels that must not enter the fit are set to 0 (then left out below, like any pixel ≤ 0)
    for row, offset in enumerate(t):  # keep t in [−h + s, h], s = 1 for a half-pixel middle, else 0
        if -window.h_min + 1 <= offset <= window.h_min:
            continue  # inside every section's window
        drop = (offset > window.h_sec) | (offset < window.half_step - window.h_sec)
        level[row][drop] = 0.0
    if outside is not None:
        level[outside] = 0.0
    if valid is not None:
        assert index is not None  # windows of a band with missing pixels are read through ``index``
        level[~valid.ravel().take(index)] = 0.0
    if window.plateau is not None:
        level[(values >= window.saturation) & window.plateau[None, :]] = 0.0
    left_out = np.less_equal(level, 0.0, out=ws.array("igcf.left_out", rows_shape, bool))
    n_used = len(t) - np.add.reduce(left_out, axis=0, dtype=np.uint8 if len(t) <= 255 else np.uint32)
    np.copyto(level, LOG_FLOOR, where=left_out)
    # weight = I² and weight·ln I side by side, so one matrix product gives all eight moment sums
    sums_input = ws.array("igcf.sums_input", (len(t), 2 * n), np.float32)
    weight, weighted_log = sums_input[:, :n], sums_input[:, n:]
    np.multiply(level, level, out=weight)
    np.log(level, out=weighted_log)
    weighted_log *= weight
    sums32 = np.matmul(_powers(window.h_max), sums_input, out=ws.array("igcf.sums32", (5, 2 * n), np.float32))
    return [*sums32[:, :n], *sums32[:3, n:]], n_used


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
