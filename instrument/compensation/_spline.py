"""CSF: cubic smoothing spline of error against measured value (paper eqs 18–23, method.md §4).

The paper fits a cubic B-spline (eqs 19–22 are the uniform cubic B-spline basis). We fit the
*smoothing* spline (the interpolating one chases noise): minimise

    Σ w_i (y_i − g(x_i))² + λ ∫ g''(x)² dx,

whose minimiser is the natural cubic spline with knots at the data (Reinsch 1967). λ is chosen
by generalised cross-validation (GCV) or by exact leave-one-point-out error, both searched on a
*logarithmic* grid of λ and refined — scipy's ``make_smoothing_spline(lam=None)`` searches a
linear interval and over-smooths short, low-noise calibration curves by tens of µm.

End intervals. Natural end conditions force g'' = 0 at both ends, where real error curves bend.
With ``end_curvature=True`` the curve is g = s + c·u² with s the natural spline and c unpenalised
(a partial spline): the penalty becomes ∫ (g'' − 2c)², so the curvature at both ends is the
fitted c instead of 0. ``trend_degree`` instead fits a polynomial first and smooths what is left.
Beyond the knots every curve here continues linearly.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # scipy's interpolation and optimisation load when a spline is fitted or evaluated
    from scipy.interpolate import CubicSpline


def ripple_columns(u: np.ndarray, omegas: np.ndarray) -> np.ndarray:
    """(n, 2k) columns sin(ω_1 u) … sin(ω_k u), cos(ω_1 u) … cos(ω_k u)."""
    phase = np.asarray(u, dtype=float).ravel()[:, None] * np.asarray(omegas, dtype=float)[None, :]
    return np.hstack([np.sin(phase), np.cos(phase)])


def reinsch_penalty(u: np.ndarray) -> np.ndarray:
    """K = Q R⁻¹ Qᵀ, so that gᵀ K g = ∫ g''² of the natural spline through (u, g).

    Parameters
    ----------
    u : (n,) sorted distinct knots, n ≥ 3

    Returns
    -------
    (n, n) symmetric positive semi-definite matrix (null space: constant and linear functions).
    """
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
    k = q @ np.linalg.solve(r, q.T)
    return 0.5 * (k + k.T)


def natural_spline_basis(knots: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Matrix B with B @ values = natural cubic spline through (knots, values) at ``u``, continued
    linearly beyond the knots."""
    from scipy.interpolate import CubicSpline
    u = np.atleast_1d(np.asarray(u, dtype=float))
    spline = CubicSpline(knots, np.eye(knots.size), bc_type="natural")
    inside = np.clip(u, knots[0], knots[-1])
    return spline(inside) + spline(inside, 1) * (u - inside)[:, None]


def curvature_column(u: np.ndarray, lo: float = -1.0, hi: float = 1.0) -> np.ndarray:
    """u² inside [lo, hi], continued linearly beyond (the unpenalised end-curvature term)."""
    u = np.asarray(u, dtype=float)
    inside = np.clip(u, lo, hi)
    return inside**2 + 2.0 * inside * (u - inside)


class PartialSpline:
    """Smoother of min Σ w (y − s − X·β)² + λ sᵀ K s: natural-spline knot values s and free (unpenalised)
    coefficients β of the columns X, for any λ from one eigendecomposition.

    Parameters
    ----------
    u : (n,) sorted distinct knots
    w : (n,) positive weights (normalised here to mean 1)
    columns : (n, p) unpenalised columns; default the end-curvature term ``curvature_column(u)``
        alone (p = 1). A ripple adds its sine and cosine (``instrument.compensation._ripple``).
    """

    def __init__(self, u: np.ndarray, w: np.ndarray, columns: np.ndarray | None = None):
        self.w = np.asarray(w, dtype=float) / np.mean(w)
        sw = np.sqrt(self.w)
        d, vecs = np.linalg.eigh(reinsch_penalty(u) / np.outer(sw, sw))
        self.eigenvalues = np.clip(d, 0.0, None)
        self.left, self.right = vecs / sw[:, None], vecs.T * sw[None, :]  # W^-½ V and Vᵀ W^½
        self.columns = curvature_column(u)[:, None] if columns is None else np.asarray(columns, dtype=float)

    def plain(self, lam: float) -> np.ndarray:
        """Hat matrix of the natural smoothing spline alone (no unpenalised columns)."""
        return (self.left * (1.0 / (1.0 + lam * self.eigenvalues))) @ self.right

    def smoothers(self, lams: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Hat matrices (L, n, n) for every λ of ``lams`` (fitted = hat @ y) and the (L, n + p, n) maps
        from y to [s; β]."""
        shrink = 1.0 / (1.0 + np.asarray(lams, dtype=float)[:, None] * self.eigenvalues[None, :])
        plain = (self.left[None] * shrink[:, None, :]) @ self.right
        x = self.columns
        plain_x = plain @ x
        m_x = self.w[:, None] * (x[None] - plain_x)  # M X with M = W (I − S), symmetric
        gram = np.swapaxes(m_x, -1, -2) @ x
        if x.shape[1] == 1:  # the end curvature alone (λ → 0 makes it vanish: keep it finite)
            coefficient_map = np.swapaxes(m_x, -1, -2) / np.maximum(gram, 1e-300)
        else:
            coefficient_map = np.linalg.pinv(gram, hermitian=True) @ np.swapaxes(m_x, -1, -2)
        s_map = plain - plain_x @ coefficient_map
        return s_map + x @ coefficient_map, np.concatenate([s_map, coefficient_map], axis=1)

    def smoother(self, lam: float) -> tuple[np.ndarray, np.ndarray]:
        """Hat matrix (fitted = hat @ y) and the (n + p, n) map from y to [s; β]."""
        hats, maps = self.smoothers(np.array([lam]))
        return hats[0], maps[0]


@dataclass(frozen=True)
class SmoothingFit:
    """Fitted values at the knots plus what the λ search found."""

    fitted: np.ndarray
    curvature: float
    lam: float
    effective_dof: float
    criterion_value: float


def smooth(u: np.ndarray, y: np.ndarray, w: np.ndarray, criterion: str = "gcv", lam: float | None = None,
           end_curvature: bool = False) -> SmoothingFit:
    """Weighted cubic smoothing spline at sorted, distinct abscissae ``u``.

    Parameters
    ----------
    u : (n,) sorted distinct abscissae (best scaled to [−1, 1])
    y : (n,) values
    w : (n,) positive weights (e.g. the number of repeats averaged)
    criterion : "gcv" (generalised cross-validation) or "loo" (exact leave-one-out over the
        interior points, i.e. leave one calibration point out when ``y`` are point means)
    lam : fixed smoothing parameter; searched when None
    end_curvature : add the unpenalised u² term (curvature at the ends, see the module text)

    Returns
    -------
    SmoothingFit
        ``fitted`` are the natural-spline values s at the knots (the u² term excluded).
    """
    from scipy.optimize import minimize_scalar
    n = u.size
    if n < 3:
        raise ValueError(f"a smoothing spline needs at least 3 distinct points, got {n}")
    if criterion not in ("gcv", "loo"):
        raise ValueError(f"criterion must be 'gcv' or 'loo', got {criterion!r}")
    w = w / w.mean()
    sw = np.sqrt(w)
    penalty = reinsch_penalty(u)
    # one eigendecomposition serves every λ: S(λ) = W^-½ V diag(1/(1 + λd)) Vᵀ W^½
    d, vecs = np.linalg.eigh(penalty / np.outer(sw, sw))
    d = np.clip(d, 0.0, None)
    z_y = vecs.T @ (sw * y)
    z_t = vecs.T @ (sw * curvature_column(u)) if end_curvature else np.zeros(n)
    interior = np.arange(n)[1:-1]

    def fits(log_lams: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Criterion, spline values, curvature and dof for each λ (rows), all at once."""
        shrink = 1.0 / (1.0 + np.exp(log_lams)[:, None] * d[None, :])
        leverage = shrink @ (vecs**2).T
        dof = shrink.sum(axis=1)
        curvature = np.zeros(log_lams.size)
        if end_curvature:  # profile out the unpenalised u² coefficient (partial spline)
            rest = (1.0 - shrink) * z_t[None, :]
            norm = np.maximum(np.sum(rest * z_t[None, :], axis=1), 1e-300)
            curvature = np.sum(rest * z_y[None, :], axis=1) / norm
            along = rest @ vecs.T
            leverage = leverage + along**2 / norm[:, None]
            dof = dof + np.sum(along**2, axis=1) / norm
        values = (shrink * (z_y[None, :] - curvature[:, None] * z_t[None, :])) @ vecs.T / sw[None, :]
        fitted = values + curvature[:, None] * curvature_column(u)[None, :]
        resid = y[None, :] - fitted
        if criterion == "gcv":
            value = np.sum(w * resid**2, axis=1) / n / np.maximum(1.0 - dof / n, 1e-9) ** 2
        else:
            loo = resid / np.maximum(1.0 - leverage, 1e-12)
            value = np.mean(loo[:, interior] ** 2, axis=1)
        return value, values, curvature, dof, fitted

    if lam is None:
        positive = d[d > 1e-9 * d.max()]
        grid = np.linspace(np.log(1e-6 / positive.max()), np.log(1e6 / positive.min()), 121)
        values = fits(grid)[0]
        best = int(np.argmin(values))
        lo, hi = grid[max(best - 1, 0)], grid[min(best + 1, grid.size - 1)]
        res = minimize_scalar(lambda g: float(fits(np.array([g]))[0][0]), bounds=(lo, hi), method="bounded",
                              options={"xatol": 1e-3})
        log_lam = float(res.x) if res.fun <= values[best] else float(grid[best])
    else:
        log_lam = float(np.log(lam))
    value, spline_values, curvature, dof, _ = fits(np.array([log_lam]))
    return SmoothingFit(spline_values[0], float(curvature[0]), float(np.exp(log_lam)), float(dof[0]), float(value[0]))


@dataclass(frozen=True)
class SplineCurve:
    """Polynomial trend plus natural cubic spline through the smoothed values (plus c·u², plus ripples).

    Beyond the knots the trend, spline and u² term continue linearly; a ripple (a_k sin ω_k u +
    b_k cos ω_k u, ``ripple_omegas`` and ``ripple_coefficients`` = [a_1 … a_k, b_1 … b_k]) goes on
    as it is, as periodic errors do.
    """

    center: float
    half_span: float
    trend: np.ndarray  # polynomial coefficients in u = (x − center)/half_span, highest first
    knots_u: np.ndarray
    values: np.ndarray
    lam: float
    effective_dof: float
    curvature: float = 0.0
    ripple_omegas: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ripple_coefficients: np.ndarray = field(default_factory=lambda: np.zeros(0))

    kind = "smoothing_spline"

    @property
    def ripple_periods(self) -> np.ndarray:
        """Periods of the ripples in the measured unit (m or rad)."""
        return 2.0 * np.pi * self.half_span / self.ripple_omegas

    def _u(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, dtype=float) - self.center) / self.half_span

    @cached_property
    def _spline(self) -> CubicSpline:
        from scipy.interpolate import CubicSpline
        return CubicSpline(self.knots_u, self.values, bc_type="natural")

    def predict(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        u = self._u(x).ravel()
        lo, hi = float(self.knots_u[0]), float(self.knots_u[-1])
        inside = np.clip(u, lo, hi)
        trend = np.polyval(self.trend, inside) + np.polyval(np.polyder(self.trend), inside) * (u - inside)
        spline = self._spline(inside) + self._spline(inside, 1) * (u - inside)
        ripple = ripple_columns(u, self.ripple_omegas) @ self.ripple_coefficients if self.ripple_omegas.size else 0.0
        return (trend + spline + self.curvature * curvature_column(u, lo, hi) + ripple).reshape(x.shape)

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
            "curvature": self.curvature,
            # only when present, so a curve without ripple is written as before (format 2)
            **({"ripple_omegas": self.ripple_omegas.tolist(), "ripple_coefficients": self.ripple_coefficients.tolist()}
               if self.ripple_omegas.size else {}),
        }

    @classmethod
    def from_dict(cls, d: dict) -> SplineCurve:
        omegas = np.asarray(d.get("ripple_omegas", []), dtype=float)
        coefficients = np.asarray(d.get("ripple_coefficients", []), dtype=float)
        if coefficients.size != 2 * omegas.size:
            raise ValueError(f"a ripple needs 2 coefficients per frequency: {omegas.size} frequencies, "
                             f"{coefficients.size} coefficients")
        return cls(float(d["center"]), float(d["half_span"]), np.asarray(d["trend"], dtype=float),
                   np.asarray(d["knots_u"], dtype=float), np.asarray(d["values"], dtype=float), float(d["lam"]),
                   float(d["effective_dof"]), float(d.get("curvature", 0.0)), omegas, coefficients)


def scaled_points(x: np.ndarray, y: np.ndarray, w: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """Point means sorted by x, with x scaled to u ∈ [−1, 1] as every curve here stores it.

    Returns
    -------
    u, y, w, center, half_span : sorted arrays (w default equal) and u = (x − center) / half_span

    Raises
    ------
    ValueError
        The points span no range.
    """
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    w = np.ones_like(x) if w is None else np.asarray(w, dtype=float)
    order = np.argsort(x)
    x, y, w = x[order], y[order], w[order]
    center, half_span = 0.5 * (x[0] + x[-1]), 0.5 * (x[-1] - x[0])
    if not half_span > 0:
        raise ValueError("the calibration points must span a non-zero range")
    return (x - center) / half_span, y, w, float(center), float(half_span)


def fit_spline_curve(x: np.ndarray, y: np.ndarray, w: np.ndarray | None = None, *, criterion: str = "gcv",
                     trend_degree: int = 0, end_curvature: bool = False, lam: float | None = None) -> SplineCurve:
    """Fit the CSF curve to point means.

    Parameters
    ----------
    x, y : (n,) distinct abscissae (any order) and values
    w : (n,) weights (repeat counts); default equal
    criterion : "gcv" or "loo" (see ``smooth``)
    trend_degree : polynomial fitted first by weighted least squares (0: none)
    end_curvature : let the ends bend (unpenalised u² term)
    lam : fixed smoothing λ (for u = x scaled to [−1, 1] and weights of mean 1); None searches it

    Returns
    -------
    SplineCurve
    """
    u, y, w, center, half_span = scaled_points(x, y, w)
    trend = np.zeros(1)
    if trend_degree > 0:
        trend = np.polyfit(u, y, trend_degree, w=np.sqrt(w))
    fit = smooth(u, y - np.polyval(trend, u), w, criterion, lam=lam, end_curvature=end_curvature)
    return SplineCurve(center, half_span, trend, u, fit.fitted, fit.lam, fit.effective_dof, fit.curvature)
