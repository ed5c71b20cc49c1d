"""Robust straight-line fit of stripe centre points: Tukey-bisquare IRLS (method.md §2.3)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

BISQUARE_TUNING = 4.685  # Tukey's constant: 95 % efficiency on Gaussian residuals
MAD_TO_SIGMA = 0.6745  # MAD of a unit normal


class LineFit(NamedTuple):
    """Result of :func:`fit_line_bisquare`: ``dependent = intercept + slope · independent``.

    Attributes
    ----------
    intercept, slope : float
        Line coefficients in the input's units.
    weights : (N,) ndarray
        Final bisquare weights in [0, 1]; 0 marks a point rejected as an outlier.
    residual_rms : float
        Weighted RMS of the perpendicular distances of the points from the line.
    iterations : int
        Reweighting iterations done (0 = the OLS start already met the tolerance).
    converged : bool
        Whether the relative coefficient change fell below ``tol``.
    """

    intercept: float
    slope: float
    weights: np.ndarray
    residual_rms: float
    iterations: int
    converged: bool


def _median(x):
    """Median by partial sort (np.median's overhead dominates on a few hundred points)."""
    n = len(x)
    k = n // 2
    if n % 2:
        return float(np.partition(x, k)[k])
    part = np.partition(x, (k - 1, k))
    return 0.5 * float(part[k - 1] + part[k])


def _weighted_line(u, v, w):
    """Weighted least squares of v = a + b·u (u already centred near 0)."""
    sw = w.sum()
    su = w @ u
    sv = w @ v
    suu = w @ (u * u)
    suv = w @ (u * v)
    det = sw * suu - su * su
    if not det > 0:
        raise ValueError("line fit is degenerate: fewer than two distinct points carry weight")
    b = (sw * suv - su * sv) / det
    a = (sv - b * su) / sw
    return a, b


def fit_line_bisquare(points, *, independent=0, tuning=BISQUARE_TUNING, tol=1e-7, max_iter=50):
    """Fit a straight line to 2-D points by iteratively reweighted least squares (Tukey's biweight).

    Starts from ordinary least squares, then repeats: residual scale s = MAD/0.6745 (median absolute
    residual from the current line, so at least half the points keep a weight), weights
    w = (1 − (r / (tuning·s))²)² for |r| < tuning·s and 0 beyond, weighted least squares — until the
    coefficient change is below ``tol`` relative to the coefficients (the slope measured as its
    effect over the half-range of the points).

    Parameters
    ----------
    points : (N, 2) array_like
        Points (x, y).
    independent : {0, 1}
        Column of the independent variable: 0 fits y = a + b·x (a near-horizontal stripe), 1 fits
        x = a + b·y (a near-vertical stripe). Residuals are taken along the dependent coordinate.
    tuning : float
        Bisquare tuning constant (4.685 by default).
    tol : float
        Relative coefficient change at which to stop.
    max_iter : int
        Upper bound on reweighting iterations.

    Returns
    -------
    LineFit

    Raises
    ------
    ValueError
        Fewer than two distinct points, or a wrongly shaped input.
    """
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points must have shape (N, 2), got {pts.shape}")
    if independent not in (0, 1):
        raise ValueError("independent must be 0 (fit y(x)) or 1 (fit x(y))")
    u_raw = pts[:, independent]
    v = pts[:, 1 - independent]
    if len(u_raw) < 2:
        raise ValueError("line fit needs at least two points")
    u0 = u_raw.mean()
    u = u_raw - u0  # centring keeps the 2×2 normal equations well conditioned
    lever = max(np.abs(u).max(), 1e-12)
    weights = np.ones_like(u)
    a, b = _weighted_line(u, v, weights)
    iterations, converged = 0, False
    for iterations in range(1, max_iter + 1):  # noqa: B007 (the count is returned)
        r = v - (a + b * u)
        mad = _median(np.abs(r))  # about the fit, as robustfit: ≥ half the points keep weight
        scale = max(mad / MAD_TO_SIGMA, 1e-12 * (1.0 + np.abs(v).max()))
        z = r / (tuning * scale)
        weights = np.where(np.abs(z) < 1.0, (1.0 - z * z) ** 2, 0.0)
        a_new, b_new = _weighted_line(u, v, weights)
        change = max(abs(a_new - a), abs(b_new - b) * lever)
        size = max(abs(a_new), abs(b_new) * lever, 1.0)
        a, b = a_new, b_new
        if change <= tol * size:
            converged = True
            break
    r_perp = (v - (a + b * u)) / np.hypot(1.0, b)
    residual_rms = float(np.sqrt((weights @ (r_perp * r_perp)) / weights.sum()))
    return LineFit(float(a - b * u0), float(b), weights, residual_rms, iterations, converged)
