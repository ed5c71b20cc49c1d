"""Ripple: periodic error terms only a few calibration steps long (issue 25).

Angle references and robot axes carry periodic errors — encoder eccentricity and its harmonics,
gear and harmonic-drive ripple — whose period can be only a few calibration steps. A smoothing
spline, a polynomial or a Gaussian process whose length scale is bounded by the grid step cannot
follow such a ripple *between* the calibration points even where it fits the points themselves:
a smooth curve through three samples per period is not a sinusoid. A sinusoid whose period the
data determine can. The model, on the aligned point means (u = measured value scaled to [−1, 1],
weights of mean 1):

    y ≈ s(u) + c·u² + Σ_k (a_k·sin ω_k u + b_k·cos ω_k u)

with s the natural spline penalised by λ∫s''² and c, a_k, b_k unpenalised. For fixed (λ, ω) it is
a linear smoother (``PartialSpline`` with the ripple's sine and cosine as extra columns), so its
leave-one-point-out residuals are exact in closed form.

What the grid can resolve. Sampled on a uniform grid of step h, a ripple of period P > 2h (the
Nyquist limit) is seen as itself; one of period P < 2h is seen exactly as a longer alias
(1.5h and 0.75h both look like 3h: on the grid f and k ± f cycles per step coincide), and near
2h its phase is lost (at exactly 2h its sine vanishes at every point). In the paper's design the
groups revisit the same nominal points (start positions within ±0.01 mm, 0.2 % of a 5 mm step;
their error offsets shift the measured value by well under 1 % of a step), so they add repeats,
not positions: nothing in such data can tell a ripple of 1.5 steps from one of 3 steps. The
search looks for periods in ``PERIOD_RANGE`` (2.5–8 steps), where the grid determines a period
uniquely; longer periods are the spline's. What it finds is reported (``RippleSearch.periods_steps``,
a model's ``details["ripple_periods_steps"]``), so a user who knows the mechanism (a gear ratio,
an encoder's line count) can check it.

Search. Every period of a grid over ``PERIOD_RANGE`` (8 frequencies per 1/span) and every λ of a
logarithmic grid are scored at once by the exact leave-one-point-out mean square over the interior
points; the best period is refined, then a second one is searched beside it (a harmonic).
Acceptance. The period search tries many frequencies, and on a smooth curve one of them always
helps a little by chance; near the ends, where a smooth curve bends fast, a sinusoid of 2.5–3
steps can even cut the leave-one-point-out error of a spline by half (3 of 30 smooth test curves)
while it makes the curve between the points worse. A ripple is therefore kept only when

- it lowers the leave-one-point-out mean square by more than ``ACCEPT_Z`` standard errors of the
  paired per-point difference, and, when the noise is known (repeats),
- its amplitude is significant: (a, b) against their covariance from the point means' noise gives
  χ² ≥ ``MIN_CHI2`` (2 degrees of freedom; the spurious sinusoids above reached 3.6–11, real
  ripples of 3.5–11× an observation's noise 700–7000), and
- its amplitude is at least ``MIN_AMPLITUDE`` of one observation's noise: a ripple that small
  adds less than 6 % to the held-out RMS when it is left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from instrument.compensation._memo import Memo, digest
from instrument.compensation._spline import (
    PartialSpline,
    SplineCurve,
    curvature_column,
    ripple_columns,
    scaled_points,
)

#: Periods searched, in grid steps (median spacing of the calibration points).
PERIOD_RANGE = (2.5, 8.0)
#: Frequencies searched per 1/span (the resolution of one record's length).
OVERSAMPLING = 8
#: At most this many ripples (a fundamental and one harmonic).
MAX_RIPPLES = 2
#: λ grid of the joint search (refined afterwards).
N_LAMBDAS = 25
#: Acceptance (see the module text): paired z of the leave-one-point-out improvement, χ² of the
#: amplitude against its noise, least amplitude in units of one observation's noise.
ACCEPT_Z = 2.0
MIN_CHI2 = 30.0
MIN_AMPLITUDE = 0.5


@dataclass(frozen=True)
class RippleSearch:
    """What ``find_ripples`` found on scaled point means.

    Attributes
    ----------
    omegas : (k,) angular frequencies in u (k = 0: no ripple kept)
    lam : smoothing λ of the spline beside them
    heldout_ms : leave-one-point-out mean square over the interior points, with the ripples
    plain_ms : the same without any ripple (the CSF with end curvature, λ by the same criterion)
    step_u : grid step in u (periods in steps = 2π / (ω · step_u))
    """

    omegas: np.ndarray
    lam: float
    heldout_ms: float
    plain_ms: float
    step_u: float

    @property
    def periods_steps(self) -> np.ndarray:
        return 2.0 * np.pi / (self.omegas * self.step_u)


class _Scan:
    """Leave-one-point-out scores of many (λ, columns) pairs at once, from one eigendecomposition."""

    def __init__(self, u: np.ndarray, y: np.ndarray, w: np.ndarray):
        self.u, self.y = u, y
        self.spline = PartialSpline(u, w)
        self.w = self.spline.w
        d = self.spline.eigenvalues
        positive = d[d > 1e-9 * d.max()]
        self.log_lams = np.linspace(np.log(1e-6 / positive.max()), np.log(1e6 / positive.min()), N_LAMBDAS)
        self.interior = np.arange(u.size)[1:-1]
        self.base = curvature_column(u)[:, None]
        self.grid = self.smoothers(self.log_lams)

    def smoothers(self, log_lams: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Plain spline hat matrices S (L, n, n), their diagonals and (I − S) y."""
        shrink = 1.0 / (1.0 + np.exp(log_lams)[:, None] * self.spline.eigenvalues[None, :])
        s = (self.spline.left[None] * shrink[:, None, :]) @ self.spline.right
        return s, np.einsum("lii->li", s), self.y[None, :] - s @ self.y

    def loo(self, x: np.ndarray, smoothers: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
            ) -> np.ndarray:
        """Leave-one-out residuals (L, F, n) for the column sets x (F, n, p) at every λ of ``smoothers``
        (default: the search grid)."""
        s, s_diag, s_resid = self.grid if smoothers is None else smoothers
        z = x[None] - s[:, None] @ x[None]  # (I − S) X, (L, F, n, p)
        m_x = self.w[:, None] * z  # M X with M = W (I − S)
        gram = np.swapaxes(x, -1, -2)[None] @ m_x  # Xᵀ M X, (L, F, p, p)
        p = x.shape[2]
        gram = gram + (1e-12 * np.trace(gram, axis1=-2, axis2=-1) / p)[..., None, None] * np.eye(p)
        solved = np.linalg.solve(gram, np.swapaxes(m_x, -1, -2))  # (Xᵀ M X)⁻¹ (M X)ᵀ, (L, F, p, n)
        beta = solved @ self.y
        resid = s_resid[:, None, :] - (z @ beta[..., None])[..., 0]
        leverage = s_diag[:, None, :] + np.sum(z * np.swapaxes(solved, -1, -2), axis=-1)
        return resid / np.maximum(1.0 - leverage, 1e-12)

    def scores(self, x: np.ndarray, smoothers: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
               ) -> np.ndarray:
        """Leave-one-point-out mean square over the interior points, (L, F)."""
        return np.mean(self.loo(x, smoothers)[..., self.interior] ** 2, axis=-1)

    def columns(self, omegas: np.ndarray) -> np.ndarray:
        return np.hstack([self.base, ripple_columns(self.u, omegas)])

    def best(self, omegas: np.ndarray) -> tuple[float, float, np.ndarray]:
        """(mean square, log λ, interior squared residuals) of the best λ for these ripples, λ refined."""
        from scipy.optimize import minimize_scalar
        x = self.columns(omegas)[None]
        grid = self.scores(x)[:, 0]
        k = int(np.argmin(grid))
        lo, hi = self.log_lams[max(k - 1, 0)], self.log_lams[min(k + 1, self.log_lams.size - 1)]
        res = minimize_scalar(lambda g: float(self.scores(x, self.smoothers(np.array([g])))[0, 0]), bounds=(lo, hi),
                              method="bounded", options={"xatol": 1e-2})
        log_lam = float(res.x) if res.fun <= grid[k] else float(self.log_lams[k])
        squares = self.loo(x, self.smoothers(np.array([log_lam])))[0, 0, self.interior] ** 2
        return float(np.mean(squares)), log_lam, squares


def _held_out_better(previous: np.ndarray, candidate: np.ndarray) -> bool:
    """The candidate's interior leave-one-point-out squares beat the previous model's by ``ACCEPT_Z``
    standard errors of the paired difference."""
    gain = previous - candidate
    se = float(np.std(gain, ddof=1) / np.sqrt(gain.size))
    return float(np.mean(gain)) > ACCEPT_Z * se


def _amplitude_significant(u: np.ndarray, y: np.ndarray, w: np.ndarray, omegas: np.ndarray, log_lam: float,
                           noise_variance: float) -> bool:
    """The last ripple's (a, b) have χ² ≥ ``MIN_CHI2`` against their covariance (point mean i has
    variance noise_variance / w_i) and an amplitude of at least ``MIN_AMPLITUDE`` observation sigmas."""
    columns = np.hstack([curvature_column(u)[:, None], ripple_columns(u, omegas)])
    _, parameters = PartialSpline(u, w, columns).smoother(float(np.exp(log_lam)))
    k, n = omegas.size, u.size
    rows = parameters[[n + k, n + 2 * k]]  # after the knot values and the end curvature: sines, then cosines
    ab = rows @ y
    covariance = (rows * (noise_variance / w)[None, :]) @ rows.T
    chi2 = float(ab @ np.linalg.pinv(covariance, hermitian=True) @ ab)
    return chi2 >= MIN_CHI2 and float(np.hypot(*ab)) >= MIN_AMPLITUDE * np.sqrt(noise_variance)


def find_ripples(u: np.ndarray, y: np.ndarray, w: np.ndarray, *, noise_variance: float | None = None,
                 max_ripples: int = MAX_RIPPLES) -> RippleSearch:
    """Search for ripples of ``PERIOD_RANGE`` steps in point means (see the module text).

    Parameters
    ----------
    u : (n,) sorted distinct abscissae scaled to [−1, 1]
    y : (n,) point means (any unit; best scaled to unit spread)
    w : (n,) repeat counts (point mean i has variance noise_variance / w_i)
    noise_variance : variance of one observation in y's unit (the noise floor squared), or None
        (unknown, or 0 as repeats that agree exactly give: only the paired held-out test guards)
    max_ripples : int

    Returns
    -------
    RippleSearch
        Computed once per set of arguments and shared (CSF + ripple and CSF-PPSO-ESN search the
        same folds).
    """
    u, y, w = (np.asarray(a, dtype=float) for a in (u, y, w))
    if noise_variance is not None and not noise_variance > 0:
        noise_variance = None
    key = digest(u, y, w, noise_variance, max_ripples)
    return _SEARCHES.get(key, lambda: _search(u, y, w, noise_variance, max_ripples))


_SEARCHES: Memo[RippleSearch] = Memo()


def _search(u: np.ndarray, y: np.ndarray, w: np.ndarray, noise_variance: float | None, max_ripples: int
            ) -> RippleSearch:
    from scipy.optimize import minimize_scalar
    step_u = float(np.median(np.diff(u)))
    span_steps = float(u[-1] - u[0]) / step_u
    scan = _Scan(u, y, w)
    plain_ms, plain_lam, plain_squares = scan.best(np.zeros(0))
    f_lo, f_hi = 1.0 / PERIOD_RANGE[1], 1.0 / PERIOD_RANGE[0]
    frequencies = np.linspace(f_lo, f_hi, int(np.ceil((f_hi - f_lo) * span_steps * OVERSAMPLING)) + 1)
    omega_of = lambda f: 2.0 * np.pi * f / step_u
    kept = np.zeros(0)
    current = (plain_ms, plain_lam, plain_squares)
    if u.size < 8:  # fewer points than a ripple, the spline and its end curvature can share
        return RippleSearch(kept, float(np.exp(plain_lam)), plain_ms, plain_ms, step_u)
    for _ in range(max_ripples):
        candidates = np.stack([scan.columns(np.append(kept, omega_of(f))) for f in frequencies])
        grid = scan.scores(candidates).min(axis=0)
        if kept.size:  # a second ripple next to the first one is not a ripple
            near = np.abs(frequencies - kept[0] * step_u / (2 * np.pi)) < 1.0 / span_steps
            grid[near] = np.inf
        k = int(np.argmin(grid))
        df = frequencies[1] - frequencies[0]
        res = minimize_scalar(
            lambda f, kept=kept: float(scan.scores(scan.columns(np.append(kept, omega_of(f)))[None]).min()),
            bounds=(max(frequencies[k] - df, f_lo), min(frequencies[k] + df, f_hi)), method="bounded",
            options={"xatol": 1e-4})
        f_best = float(res.x) if res.fun <= grid[k] else float(frequencies[k])
        if min(f_best - f_lo, f_hi - f_best) < 0.01 * (f_hi - f_lo):
            break  # at the edge of the range: what helped was no ripple of the range (a spline's or an alias)
        trial = np.append(kept, omega_of(f_best))
        found = scan.best(trial)
        if not _held_out_better(current[2], found[2]) or (
                noise_variance is not None and not _amplitude_significant(u, y, w, trial, found[1], noise_variance)):
            break
        kept, current = trial, found
    return RippleSearch(kept, float(np.exp(current[1])), current[0], plain_ms, step_u)


def fit_ripple_spline(x: np.ndarray, y: np.ndarray, w: np.ndarray | None = None, *,
                      noise_variance: float | None = None, max_ripples: int = MAX_RIPPLES) -> SplineCurve:
    """CSF with end curvature plus the ripples ``find_ripples`` keeps, fitted to point means.

    Parameters
    ----------
    x, y : (n,) distinct abscissae (any order) and point means
    w : (n,) weights (repeat counts); default equal
    noise_variance : variance of one observation (the noise floor squared), or None
    max_ripples : int

    Returns
    -------
    SplineCurve
        With ``ripple_omegas`` empty when no ripple was kept (then the CSF with end curvature,
        λ by leave-one-point-out).
    """
    u, y, w, center, half_span = scaled_points(x, y, w)
    scale = float(np.std(y)) or 1.0
    search = find_ripples(u, y / scale, w, noise_variance=None if noise_variance is None else noise_variance / scale**2,
                          max_ripples=max_ripples)
    columns = np.hstack([curvature_column(u)[:, None], ripple_columns(u, search.omegas)])
    spline = PartialSpline(u, w, columns)
    hat, parameters = spline.smoother(search.lam)
    theta = parameters @ y
    n = u.size
    return SplineCurve(center, half_span, np.zeros(1), u, theta[:n], search.lam,
                       float(np.trace(hat)), float(theta[n]), search.omegas, theta[n + 1:])
