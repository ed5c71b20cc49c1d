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
    return bisquare_lines([independent], [dependent], tuning=tuning, tol=tol, max_iter=max_iter)[0]


def _lines_from_sums(sums):
    """(a, b) arrays of v = a + b·u from rows of weighted sums Σw, Σwu, Σwv, Σwu², Σwuv."""
    sw, su, sv, suu, suv = sums.T
    det = sw * suu - su * su
    if not np.all(det > 0):
        raise ValueError("line fit is degenerate: fewer than two distinct points carry weight")
    b = (sw * suv - su * sv) / det
    return (sv - b * su) / sw, b


def bisquare_lines(independents, dependents, *, tuning=BISQUARE_TUNING, tol=1e-7, max_iter=50) -> list[LineFit]:
    """:func:`bisquare_line` on several point sets at once (the six stripes of a trigger).

    Each set gets exactly the fit it would get alone (its own scale, weights, convergence test
    and iteration count); the sets only share the array operations, padded to the longest set,
    so the per-call cost of the few dozen numpy operations of an IRLS is paid once.
    """
    sizes = np.array([len(u) for u in independents])
    n_sets = len(sizes)
    # The median of each set's |residuals| by one partition of all sets at one position: set j's
    # points sit at columns pad_j … pad_j + n_j − 1 behind pad_j = c − n_j // 2 slots that sort
    # first (−1), so its middle order statistics land at columns c − 1 and c for every set.
    middle_column = int(sizes.max() // 2)
    pad = middle_column - sizes // 2
    width = int((pad + sizes).max())
    u = np.zeros((n_sets, width))
    v = np.zeros((n_sets, width))
    real = np.zeros((n_sets, width), bool)  # False: padding, which never carries weight
    u0 = np.empty(n_sets)
    for j, (independent, dependent) in enumerate(zip(independents, dependents)):
        points = slice(pad[j], pad[j] + sizes[j])
        u_raw = np.asarray(independent, dtype=float)
        u0[j] = u_raw.mean()
        u[j, points] = u_raw - u0[j]  # centring keeps the 2×2 normal equations well conditioned
        v[j, points] = dependent
        real[j, points] = True
    padding_order = np.where(np.arange(width)[None, :] < pad[:, None], -1.0, np.inf)  # before / after the points
    lever = np.maximum(np.abs(u).max(axis=1), 1e-12)
    scale_floor = 1e-12 * (1.0 + np.abs(v).max(axis=1))
    # Every weighted fit needs the same five sums: one batched product per iteration.
    moments = np.stack([real.astype(float), u, v, u * u, u * v], axis=1)  # (sets, 5, points)
    a, b = _lines_from_sums(moments.sum(axis=2))
    odd = sizes % 2 == 1  # an odd count's median is its middle point; an even one averages the two middle ones
    kth = [middle_column - 1, middle_column] if middle_column > 0 else [0]
    weights = np.zeros((n_sets, width))
    iterations = np.zeros(n_sets, int)
    converged = np.zeros(n_sets, bool)
    active = np.ones(n_sets, bool)
    for iteration in range(1, max_iter + 1):
        residual = v - (a[:, None] + b[:, None] * u)
        magnitude = np.where(real, np.abs(residual), padding_order)
        magnitude.partition(kth, axis=1)
        upper = magnitude[:, middle_column]
        mad = np.where(odd, upper, 0.5 * (magnitude[:, kth[0]] + upper))  # about the fit, as robustfit
        scale = np.maximum(mad / MAD_TO_SIGMA, scale_floor)
        # w = (1 − z²)² for |z| < 1, else 0, with z = r / (tuning·scale)
        w = residual * (1.0 / (tuning * scale))[:, None]
        np.multiply(w, w, out=w)
        np.subtract(1.0, w, out=w)
        np.maximum(w, 0.0, out=w)
        np.multiply(w, w, out=w)
        w *= real
        a_new, b_new = _lines_from_sums(np.einsum("spn,sn->sp", moments, w))
        change = np.maximum(np.abs(a_new - a), np.abs(b_new - b) * lever)
        size = np.maximum(np.maximum(np.abs(a_new), np.abs(b_new) * lever), 1.0)
        # a set that has converged keeps its fit: later iterations of the others do not touch it
        a, b = np.where(active, a_new, a), np.where(active, b_new, b)
        weights[active] = w[active]
        iterations[active] = iteration
        done = active & (change <= tol * size)
        converged |= done
        active &= ~done
        if not active.any():
            break
    r_perp = (v - (a[:, None] + b[:, None] * u)) / np.hypot(1.0, b)[:, None]
    residual_rms = np.sqrt(np.einsum("sn,sn->s", weights, r_perp * r_perp) / weights.sum(axis=1))
    return [
        LineFit(float(a[j] - b[j] * u0[j]), float(b[j]), weights[j, pad[j] : pad[j] + sizes[j]].copy(),
                float(residual_rms[j]), int(iterations[j]), bool(converged[j]))
        for j in range(n_sets)
    ]
