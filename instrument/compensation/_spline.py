"""CSF: cubic smoothing spline of error against measured value (paper eqs 18–23, method.md §4).

The paper fits a cubic B-spline (eqs 19–22 are the uniform cubic B-spline basis). We fit the
*smoothing* spline (the interpolating one chases noise): minimise

    Σ w_i (y_i − g(x_i))² + λ ∫ g''(x)² dx,

whose minimiser is the natural cubic spline with knots at the data (Reinsch 1967). λ is chosen
by generalised cross-validation (GCV) or by exact leave-one-point-out error, both searched on a
*logarithmic* grid of λ and refined — scipy's ``make_smoothing_spline(lam=None)`` searches a
linear interval and over-smooths short, low-noise calibration curves by tens of µm.

Natural end conditions force g'' = 0 at both ends, where real error curves often bend. The
optional polynomial trend (``trend_degree``) is fitted first by weighted least squares and the
spline smooths what is left, so the curvature at the ends comes from the trend.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.optimize import minimize_scalar


def _reinsch_penalty(u: np.ndarray) -> np.ndarray:
    """K = Q R⁻¹ Qᵀ, so that gᵀ K g = ∫ g''² of the natural spline through (u, g)."""
    n = u.size
    h = np.diff(u)
    q = np.zeros((n, n - 2))
    r = np.zeros((n - 2, n - 2))
    for j in range(n - 2):
        q[j, j] = 1.0 / h[j]
        q[j + 1, j] = -1.0 / h[j] - 1.0 / h[j + 1]
        q[j + 2, j] = 1.0 / h[j + 1]
        r[j, j] = (h[j] + h[j + 1]) / 3.0
        if j + 1 < n - 2:
            r[j, j + 1] = r[j + 1, j] = h[j + 1] / 6.0
    return q @ np.linalg.solve(r, q.T)


@dataclass(frozen=True)
class SmoothingFit:
    """Fitted values at the knots plus what the λ search found."""

    fitted: np.ndarray
    lam: float
    effective_dof: float
    criterion_value: float


def smooth(
    u: np.ndarray, y: np.ndarray, w: np.ndarray, criterion: str = "gcv", lam: float | None = None
) -> SmoothingFit:
    """Weighted cubic smoothing spline values at sorted, distinct abscissae ``u``.

    Parameters
    ----------
    u : (n,) sorted distinct abscissae (best scaled to about unit span)
    y : (n,) values; w : (n,) positive weights (e.g. the number of repeats averaged)
    criterion : "gcv" (generalised cross-validation) or "loo" (exact leave-one-out, i.e. leave one
        calibration point out when ``y`` are point means)
    lam : fixed smoothing parameter; searched when None.
    """
    n = u.size
    if n < 3:
        raise ValueError(f"a smoothing spline needs at least 3 distinct points, got {n}")
    if criterion not in ("gcv", "loo"):
        raise ValueError(f"criterion must be 'gcv' or 'loo', got {criterion!r}")
    sw = np.sqrt(w)
    a = _reinsch_penalty(u) / np.outer(sw, sw)
    d, vecs = np.linalg.eigh(0.5 * (a + a.T))
    d = np.clip(d, 0.0, None)
    z = vecs.T @ (sw * y)

    def evaluate(log_lam: float):
        shrink = 1.0 / (1.0 + np.exp(log_lam) * d)
        fitted = (vecs @ (shrink * z)) / sw
        resid = y - fitted
        if criterion == "gcv":
            rss = np.sum(w * resid**2)
            value = (rss / n) / (1.0 - shrink.sum() / n) ** 2
        else:
            leverage = np.einsum("ij,j,ij->i", vecs, shrink, vecs)
            value = np.sum(w * (resid / np.maximum(1.0 - leverage, 1e-12)) ** 2) / np.sum(w)
        return value, fitted, shrink.sum()

    if lam is None:
        positive = d[d > 1e-12 * d.max()]
        grid = np.linspace(np.log(1e-6 / positive.max()), np.log(1e6 / positive.min()), 121)
        values = np.array([evaluate(g)[0] for g in grid])
        best = int(np.argmin(values))
        lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, grid.size - 1)]
        res = minimize_scalar(lambda g: evaluate(g)[0], bounds=(lo, hi), method="bounded", options={"xatol": 1e-3})
        log_lam = float(res.x) if res.fun <= values[best] else float(grid[best])
    else:
        log_lam = float(np.log(lam))
    value, fitted, dof = evaluate(log_lam)
    return SmoothingFit(fitted, float(np.exp(log_lam)), float(dof), float(value))


@dataclass(frozen=True)
class SplineCurve:
    """Polynomial trend plus natural cubic spline through the smoothed residual values.

    Beyond the knots the curve continues linearly (the natural spline's own extension).
    """

    center: float
    half_span: float
    trend: np.ndarray  # polynomial coefficients in u = (x − center)/half_span, highest first
    knots_u: np.ndarray
    values: np.ndarray
    lam: float
    effective_dof: float

    kind = "smoothing_spline"

    def _u(self, x):
        return (np.asarray(x, dtype=float) - self.center) / self.half_span

    def predict(self, x):
        u = self._u(x)
        spline = CubicSpline(self.knots_u, self.values, bc_type="natural", extrapolate=True)
        lo, hi = self.knots_u[0], self.knots_u[-1]
        inside = np.clip(u, lo, hi)
        out = spline(inside) + spline(inside, 1) * (u - inside)
        return np.polyval(self.trend, u) + out

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "center": self.center,
            "half_span": self.half_span,
            "trend": self.trend.tolist(),
            "knots_u": self.knots_u.tolist(),
            "values": self.values.tolist(),
            "lam": self.lam,
            "effective_dof": self.effective_dof,
        }

    @classmethod
    def from_dict(cls, d: dict) -> SplineCurve:
        return cls(
            float(d["center"]),
            float(d["half_span"]),
            np.asarray(d["trend"], dtype=float),
            np.asarray(d["knots_u"], dtype=float),
            np.asarray(d["values"], dtype=float),
            float(d["lam"]),
            float(d["effective_dof"]),
        )


def fit_spline_curve(
    x: np.ndarray, y: np.ndarray, w: np.ndarray | None = None, *, criterion: str = "gcv", trend_degree: int = 0
) -> SplineCurve:
    """Fit the CSF curve to point means (x sorted or not; distinct)."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    w = np.ones_like(x) if w is None else np.asarray(w, dtype=float)
    order = np.argsort(x)
    x, y, w = x[order], y[order], w[order]
    center, half_span = 0.5 * (x[0] + x[-1]), 0.5 * (x[-1] - x[0])
    if not half_span > 0:
        raise ValueError("the calibration points must span a non-zero range")
    u = (x - center) / half_span
    trend = np.zeros(1)
    if trend_degree > 0:
        trend = np.polyfit(u, y, trend_degree, w=np.sqrt(w))
    fit = smooth(u, y - np.polyval(trend, u), w, criterion)
    return SplineCurve(center, half_span, trend, u, fit.fitted, fit.lam, fit.effective_dof)
