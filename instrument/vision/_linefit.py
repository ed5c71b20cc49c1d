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
    """Median by partial sort (np.median's overhead dominates on a few hundred points).

    One partition at n // 2; for an even count the lower middle is the largest of the lower part
    (a second partition point would cost three times as much).
    """
    n = len(x)
    k = n // 2
    part = np.partition(x, k)
    if n % 2:
        return float(part[k])
    return 0.5 * float(part[k] + part[:k].max())


def _median_in_place(x):
    """:func:`_median` that reorders ``x`` instead of copying it."""
    n = len(x)
    k = n // 2
    x.partition(k)
    if n % 2:
        return float(x[k])
    return 0.5 * float(x[k] + np.maximum.reduce(x[:k]))


def _weighted_line(u, v, w):
    """Weighted least squares of v = a + b·u (u already centred near 0)."""
    return _line_from_sums(w.sum(), w @ u, w @ v, w @ (u * u), w @ (u * v))


def _line_from_sums(sw, su, sv, suu, suv):
    """(a, b) of v = a + b·u from the weighted sums Σw, Σwu, Σwv, Σwu², Σwuv."""
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
    if len(pts) < 2:
        raise ValueError("line fit needs at least two points")
    return bisquare_line(pts[:, independent], pts[:, 1 - independent], tuning=tuning, tol=tol, max_iter=max_iter)


def bisquare_line(independent, dependent, *, tuning=BISQUARE_TUNING, tol=1e-7, max_iter=50) -> LineFit:
    """:func:`fit_line_bisquare` on two coordinate arrays (the fast path: no (N, 2) array).

    Fits ``dependent = intercept + slope·independent``; residuals along the dependent coordinate.
    """
    u_raw = np.asarray(independent, dtype=float)
    v = np.ascontiguousarray(dependent, dtype=float)
    u0 = np.add.reduce(u_raw) / len(u_raw)  # u_raw.mean(), without its Python-level wrapper
    u = u_raw - u0  # centring keeps the 2×2 normal equations well conditioned
    lever = max(np.maximum.reduce(np.abs(u)), 1e-12)
    # Every weighted fit needs the same five sums: one matrix–vector product per iteration.
    moments = np.empty((5, len(u)))
    moments[0] = 1.0
    moments[1] = u
    moments[2] = v
    np.multiply(u, u, out=moments[3])
    np.multiply(u, v, out=moments[4])
    a, b = _line_from_sums(*np.add.reduce(moments, axis=1))
    weights = np.ones(len(u))
    residual = np.empty(len(u))
    magnitude = np.empty(len(u))
    scale_floor = 1e-12 * (1.0 + np.maximum.reduce(np.abs(v)))
    iterations, converged = 0, False
    for iterations in range(1, max_iter + 1):  # noqa: B007 (the count is returned)
        np.multiply(u, b, out=residual)
        residual += a
        np.subtract(v, residual, out=residual)
        np.abs(residual, out=magnitude)
        mad = _median_in_place(magnitude)  # about the fit, as robustfit: ≥ half the points keep weight
        scale = max(mad / MAD_TO_SIGMA, scale_floor)
        # w = (1 − z²)² for |z| < 1, else 0, with z = r / (tuning·scale)
        np.multiply(residual, 1.0 / (tuning * scale), out=weights)
        np.multiply(weights, weights, out=weights)
        np.subtract(1.0, weights, out=weights)
        np.maximum(weights, 0.0, out=weights)
        np.multiply(weights, weights, out=weights)
        a_new, b_new = _line_from_sums(*(moments @ weights))
        change = max(abs(a_new - a), abs(b_new - b) * lever)
        size = max(abs(a_new), abs(b_new) * lever, 1.0)
        a, b = a_new, b_new
        if change <= tol * size:
            converged = True
            break
    r_perp = (v - (a + b * u)) / np.hypot(1.0, b)
    residual_rms = float(np.sqrt((weights @ (r_perp * r_perp)) / np.add.reduce(weights)))
    return LineFit(float(a - b * u0), float(b), weights, residual_rms, iterations, converged)
