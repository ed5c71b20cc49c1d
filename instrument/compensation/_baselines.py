"""Baseline curves: none, low-order polynomial, Gaussian process (numpy/scipy only)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ZeroCurve:
    """No compensation: predicted error 0."""

    kind = "none"

    def predict(self, x: np.ndarray) -> np.ndarray:
        return np.zeros(np.shape(x))

    def to_dict(self) -> dict:
        return {"kind": self.kind}

    @classmethod
    def from_dict(cls, d: dict) -> ZeroCurve:
        return cls()


@dataclass(frozen=True)
class PolynomialCurve:
    """Polynomial in u = (x − center) / half_span (coefficients highest power first)."""

    center: float
    half_span: float
    coefficients: np.ndarray

    kind = "polynomial"

    def predict(self, x: np.ndarray) -> np.ndarray:
        return np.polyval(self.coefficients, (np.asarray(x, float) - self.center) / self.half_span)

    def to_dict(self) -> dict:
        return {"kind": self.kind, "center": self.center, "half_span": self.half_span,
                "coefficients": self.coefficients.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> PolynomialCurve:
        return cls(float(d["center"]), float(d["half_span"]), np.asarray(d["coefficients"], float))


def fit_polynomial(x: np.ndarray, y: np.ndarray, w: np.ndarray, *, degree: int | None = None,
                   max_degree: int = 5) -> PolynomialCurve:
    """Weighted least-squares polynomial in u = (x − center)/half_span.

    Parameters
    ----------
    x, y, w : (n,) point means and weights
    degree : fixed degree; when None, the degree (1 … ``max_degree``) with the lowest exact
        leave-one-point-out error over the interior points (as everywhere in this package)
    max_degree : int

    Returns
    -------
    PolynomialCurve
    """
    x, y, w = (np.asarray(v, float) for v in (x, y, w))
    center, half_span = 0.5 * (x.min() + x.max()), 0.5 * (x.max() - x.min())
    u = (x - center) / half_span
    if degree is None:
        interior = (x > x.min()) & (x < x.max())
        best, best_score = 1, np.inf
        for deg in range(1, min(max_degree, x.size - 2) + 1):
            v = np.vander(u, deg + 1) * np.sqrt(w)[:, None]
            h = v @ np.linalg.pinv(v)
            resid = (y - np.polyval(np.polyfit(u, y, deg, w=np.sqrt(w)), u)) / np.maximum(1 - np.diag(h), 1e-12)
            score = np.mean(resid[interior] ** 2)
            if score < best_score:
                best, best_score = deg, score
        degree = best
    return PolynomialCurve(center, half_span, np.polyfit(u, y, degree, w=np.sqrt(w)))


@dataclass(frozen=True)
class GaussianProcessCurve:
    """GP posterior mean with a squared-exponential kernel on top of a linear trend."""

    trend: np.ndarray  # linear trend coefficients in x (highest first)
    x_train: np.ndarray
    alpha: np.ndarray
    signal_variance: float
    length_scale: float
    noise_variance: float

    kind = "gaussian_process"

    def predict(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, float)
        k = self.signal_variance * np.exp(
            -0.5 * ((x.ravel()[:, None] - self.x_train[None, :]) / self.length_scale) ** 2
        )
        return (np.polyval(self.trend, x.ravel()) + k @ self.alpha).reshape(x.shape)

    def to_dict(self) -> dict:
        return {"kind": self.kind, "trend": self.trend.tolist(), "x_train": self.x_train.tolist(),
                "alpha": self.alpha.tolist(), "signal_variance": self.signal_variance,
                "length_scale": self.length_scale, "noise_variance": self.noise_variance}

    @classmethod
    def from_dict(cls, d: dict) -> GaussianProcessCurve:
        return cls(np.asarray(d["trend"], float), np.asarray(d["x_train"], float), np.asarray(d["alpha"], float),
                   float(d["signal_variance"]), float(d["length_scale"]), float(d["noise_variance"]))


def fit_gaussian_process(x: np.ndarray, y: np.ndarray, w: np.ndarray, *, point_variance: float | None = None
                         ) -> GaussianProcessCurve:
    """GP regression on point means with hyper-parameters by maximum marginal likelihood.

    The length scale is bounded below by the grid step (median spacing of the calibration
    points): a shorter one lets the GP explain each point on its own and predict the trend
    alone between points. The noise variance of a point mean is ``point_variance / w`` with
    ``point_variance`` (variance of one observation) fitted within [¼, 4]× the given value when
    given, else free.

    Parameters
    ----------
    x, y, w : (n,) point means and weights (repeat counts)
    point_variance : variance of one observation (the noise floor squared), or None

    Returns
    -------
    GaussianProcessCurve
    """
    from scipy.linalg import cho_factor, cho_solve
    from scipy.optimize import minimize
    x, y, w = (np.asarray(v, float) for v in (x, y, w))
    order = np.argsort(x)
    x, y, w = x[order], y[order], w[order]
    trend = np.polyfit(x, y, 1, w=np.sqrt(w))
    r = y - np.polyval(trend, x)
    step = float(np.median(np.diff(x)))
    span = float(x[-1] - x[0])
    var_r = max(float(np.var(r)), 1e-300)
    if point_variance is None:
        noise_bounds = (np.log(var_r * 1e-8), np.log(var_r))
    else:
        # Repeats that agree exactly (a noise floor of 0, as replayed noise gives) must not make the
        # bounds infinite: the noise variance is then bounded below by a negligible fraction of the signal.
        point_variance = max(float(point_variance), var_r * 1e-8)
        noise_bounds = (np.log(point_variance / 4), np.log(point_variance * 4))
    bounds = [(np.log(var_r * 1e-3), np.log(var_r * 1e3)), (np.log(step), np.log(2 * span)), noise_bounds]
    d2 = (x[:, None] - x[None, :]) ** 2

    def nll(theta: np.ndarray) -> tuple[float, np.ndarray]:
        """Negative log marginal likelihood and its gradient in (log s², log ℓ, log n²)."""
        s2, ell, n2 = np.exp(theta)
        shape = np.exp(-0.5 * d2 / ell**2)
        k = s2 * shape + np.diag(n2 / w) + 1e-12 * s2 * np.eye(x.size)
        try:
            c = cho_factor(k, lower=True)
        except np.linalg.LinAlgError:
            return 1e300, np.zeros(3)
        a = cho_solve(c, r)
        inner = cho_solve(c, np.eye(x.size)) - np.outer(a, a)  # K⁻¹ − ααᵀ
        derivatives = (s2 * shape, s2 * shape * d2 / ell**2, np.diag(n2 / w))
        gradient = np.array([0.5 * np.sum(inner * dk) for dk in derivatives])
        return float(0.5 * r @ a + np.sum(np.log(np.diag(c[0])))), gradient

    starts = [np.array([np.log(var_r), np.log(ell0), np.mean(noise_bounds)])
              for ell0 in (step * 1.5, span / 4, span)]
    best = min((minimize(nll, s, jac=True, method="L-BFGS-B", bounds=bounds) for s in starts),
               key=lambda res: res.fun)
    s2, ell, n2 = np.exp(best.x)
    k = s2 * np.exp(-0.5 * d2 / ell**2) + np.diag(n2 / w) + 1e-12 * s2 * np.eye(x.size)
    alpha = cho_solve(cho_factor(k, lower=True), r)
    return GaussianProcessCurve(trend, x, alpha, float(s2), float(ell), float(n2))
