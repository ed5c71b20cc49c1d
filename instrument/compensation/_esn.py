"""CSF + ESN: smoothing spline plus echo state network, one joint linear smoother (paper §3.3–3.4).

The paper's step 4 lets the PPSO-tuned ESN improve "on the basis of" the CSF. Here both are one
model, fitted jointly to the aligned point means (u = measured value scaled to [−1, 1], y = error
scaled to unit spread, w = repeat counts):

    y ≈ s(u) + c·u² + ripple(u) + Φ(u)·b,   minimising Σ w (y − fit)² + λ·∫ s''² + μ·|b|²

- s is the natural cubic spline through its knot values (the CSF, eqs 18–23); c·u² is unpenalised,
  so the curvature at the ends is fitted instead of forced to zero (natural end conditions);
- ripple(u) = Σ a_k sin ω_k u + b_k cos ω_k u, unpenalised, at the periods the ripple search keeps
  (``instrument.compensation._ripple``; none on smooth data): a periodic error a few calibration
  steps long that neither the spline nor the reservoir's smooth features follow between points;
- Φ(u) are the ESN's features (eqs 30–32): a static map needs a constant input, so the leaky tanh
  reservoir (sparse, ``CONNECTIONS_PER_NEURON`` inputs per neuron, spectral radius ρ < 1) runs
  ``RESERVOIR_STEPS`` steps from rest with input [1, s_in·u]; its final state and u are the
  features, b the linear readout (eq 32 with f₂ the identity: the error is not bounded).

For fixed hyper-parameters the fit is a linear smoother, fitted = A·y, so the leave-one-point-out
residuals are exact in closed form: r_i / (1 − A_ii) (removing a point's weight equals refitting
without it: the natural spline through the other points is also the optimum with the knot kept).
The PPSO search of the hyper-parameters is ``instrument.compensation._csf_esn``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from instrument.compensation._spline import (
    PartialSpline,
    curvature_column,
    natural_spline_basis,
    ripple_columns,
)

RESERVOIR_STEPS = 25
CONNECTIONS_PER_NEURON = 10



@dataclass(frozen=True)
class EsnHyperparameters:
    """Reservoir size, spectral radius ρ, leak rate a, input scaling s_in, readout ridge μ (relative to
    the mean squared feature norm) and spline smoothing λ (for u on [−1, 1], unit-spread y, mean weight 1)."""

    reservoir_size: int
    spectral_radius: float
    leak_rate: float
    input_scaling: float
    ridge: float
    smoothing: float

    def to_dict(self) -> dict:
        return {
            "reservoir_size": int(self.reservoir_size),
            "spectral_radius": float(self.spectral_radius),
            "leak_rate": float(self.leak_rate),
            "input_scaling": float(self.input_scaling),
            "ridge": float(self.ridge),
            "smoothing": float(self.smoothing),
        }

    @classmethod
    def from_dict(cls, d: dict) -> EsnHyperparameters:
        return cls(int(d["reservoir_size"]), float(d["spectral_radius"]), float(d["leak_rate"]),
                   float(d["input_scaling"]), float(d["ridge"]), float(d["smoothing"]))


@dataclass(frozen=True)
class Reservoir:
    """Input weights (size, 2) for [bias, input] and sparse reservoir weights (rows, cols, values)."""

    w_in: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    values: np.ndarray

    @property
    def size(self) -> int:
        return int(self.w_in.shape[0])

    def dense(self) -> np.ndarray:
        w = np.zeros((self.size, self.size))
        w[self.rows, self.cols] = self.values
        return w


@lru_cache(maxsize=256)
def make_reservoir(size: int, spectral_radius: float, seed: int) -> Reservoir:
    """Sparse random reservoir with the given spectral radius.

    Parameters
    ----------
    size : int
        Number of neurons; each gets ``min(CONNECTIONS_PER_NEURON, size)`` inputs.
    spectral_radius : float in (0, 1)
        Echo state property.
    seed : int
        With ``size``, seeds every weight.

    Returns
    -------
    Reservoir
        Cached: a (size, ρ, seed) asked again returns the same object (treat it as read-only).
    """
    if not 0 < spectral_radius < 1:
        raise ValueError(f"spectral radius must lie in (0, 1) for the echo state property, got {spectral_radius}")
    rng = np.random.default_rng([seed, size])
    w_in = rng.uniform(-1.0, 1.0, (size, 2))
    k = min(CONNECTIONS_PER_NEURON, size)
    rows = np.repeat(np.arange(size), k)
    cols = np.concatenate([rng.choice(size, k, replace=False) for _ in range(size)])
    values = rng.normal(0.0, 1.0, rows.size)
    w = np.zeros((size, size))
    w[rows, cols] = values
    radius = float(np.max(np.abs(np.linalg.eigvals(w))))
    values = values * (spectral_radius / radius if radius > 0 else 0.0)
    return Reservoir(w_in, rows, cols, values)


def features(reservoir: Reservoir, u: np.ndarray, hyper: EsnHyperparameters,
             w_dense: np.ndarray | None = None) -> np.ndarray:
    """ESN features [state after ``RESERVOIR_STEPS`` steps of constant input, u], one row per input."""
    w_t = (reservoir.dense() if w_dense is None else w_dense).T
    u = np.asarray(u, dtype=float).ravel()
    drive = reservoir.w_in[:, 0][None, :] + hyper.input_scaling * u[:, None] * reservoir.w_in[:, 1][None, :]
    keep, leak = 1.0 - hyper.leak_rate, hyper.leak_rate
    state = leak * np.tanh(drive)  # the first step from rest
    for _ in range(RESERVOIR_STEPS - 1):
        state = keep * state + leak * np.tanh(drive + state @ w_t)
    return np.hstack([state, u[:, None]])


@dataclass(frozen=True)
class JointFit:
    """The joint smoother for fixed hyper-parameters: hat matrix and the parameters for y (the
    coefficients of the spline's unpenalised columns after the end curvature: the ripples')."""

    hat: np.ndarray
    spline_values: np.ndarray
    curvature: float
    weights: np.ndarray
    ripple_coefficients: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def loo_residuals(self, y: np.ndarray) -> np.ndarray:
        """Exact leave-one-out residuals of every point."""
        return (y - self.hat @ y) / np.maximum(1.0 - np.diag(self.hat), 1e-12)


def joint_fit(spline: PartialSpline, y: np.ndarray, phi: np.ndarray, hyper: EsnHyperparameters,
              parameters: bool = True) -> JointFit:
    """Fit spline + u² + ESN readout jointly (see the module text).

    With S the partial-spline smoother and M = W(I − S), profiling out the spline gives the readout
    in n × n algebra (G = ΦΦᵀ): Φb = G(MG + μI)⁻¹M y and fitted = S y + (I − S)Φb.

    Parameters
    ----------
    spline : the partial-spline smoother of the points (weights included)
    y : (n,) values
    phi : (n, m) ESN features at the points
    hyper : hyper-parameters (``smoothing`` λ and ``ridge`` μ are used here)
    parameters : also compute the spline values, curvature and readout weights (False: only the hat
        matrix is meaningful, the rest are zeros — what the swarm's objectives need)
    """
    n = y.size
    spline_hat, spline_map = spline.smoother(hyper.smoothing)
    m = spline.w[:, None] * (np.eye(n) - spline_hat)
    gram = phi @ phi.T
    mu = hyper.ridge * max(float(np.trace(gram)) / n, 1e-300)
    q = np.linalg.solve(m @ gram + mu * np.eye(n), m)
    hat = spline_hat + (np.eye(n) - spline_hat) @ (gram @ q)
    if not parameters:
        return JointFit(hat, np.zeros(n), 0.0, np.zeros(phi.shape[1]))
    weights = phi.T @ (q @ y)
    theta = spline_map @ (y - phi @ weights)
    return JointFit(hat, theta[:n], float(theta[n]), weights, theta[n + 1:])


@dataclass(frozen=True)
class CsfEsnCurve:
    """A trained CSF-ESN curve: error = y_scale·(s(u) + c·u² + ripple(u) + Φ(u)·b), u = (x − center)/half_span,
    ripple(u) = Σ a_k sin ω_k u + b_k cos ω_k u (``ripple_coefficients`` = [a…, b…]; none in format-2 records)."""

    hyper: EsnHyperparameters
    reservoir: Reservoir
    center: float
    half_span: float
    y_scale: float
    knots_u: np.ndarray
    spline_values: np.ndarray
    curvature: float
    weights: np.ndarray
    seed: int
    ripple_omegas: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ripple_coefficients: np.ndarray = field(default_factory=lambda: np.zeros(0))

    kind = "csf-esn"

    def predict(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        u = ((x - self.center) / self.half_span).ravel()
        lo, hi = float(self.knots_u[0]), float(self.knots_u[-1])
        fit = (natural_spline_basis(self.knots_u, u) @ self.spline_values
               + self.curvature * curvature_column(u, lo, hi) + features(self.reservoir, u, self.hyper) @ self.weights)
        if self.ripple_omegas.size:
            fit = fit + ripple_columns(u, self.ripple_omegas) @ self.ripple_coefficients
        return (fit * self.y_scale).reshape(x.shape)

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "hyper": self.hyper.to_dict(),
            "seed": int(self.seed),
            "center": self.center,
            "half_span": self.half_span,
            "y_scale": self.y_scale,
            "knots_u": self.knots_u.tolist(),
            "spline_values": self.spline_values.tolist(),
            "curvature": self.curvature,
            "w_in": self.reservoir.w_in.tolist(),
            "reservoir_rows": self.reservoir.rows.tolist(),
            "reservoir_cols": self.reservoir.cols.tolist(),
            "reservoir_values": self.reservoir.values.tolist(),
            "weights": self.weights.tolist(),
            **({"ripple_omegas": self.ripple_omegas.tolist(), "ripple_coefficients": self.ripple_coefficients.tolist()}
               if self.ripple_omegas.size else {}),
        }

    @classmethod
    def from_dict(cls, d: dict) -> CsfEsnCurve:
        reservoir = Reservoir(np.asarray(d["w_in"], float), np.asarray(d["reservoir_rows"], int),
                              np.asarray(d["reservoir_cols"], int), np.asarray(d["reservoir_values"], float))
        omegas = np.asarray(d.get("ripple_omegas", []), float)
        coefficients = np.asarray(d.get("ripple_coefficients", []), float)
        if coefficients.size != 2 * omegas.size:
            raise ValueError(f"a ripple needs 2 coefficients per frequency: {omegas.size} frequencies, "
                             f"{coefficients.size} coefficients")
        return cls(EsnHyperparameters.from_dict(d["hyper"]), reservoir, float(d["center"]), float(d["half_span"]),
                   float(d["y_scale"]), np.asarray(d["knots_u"], float), np.asarray(d["spline_values"], float),
                   float(d["curvature"]), np.asarray(d["weights"], float), int(d["seed"]), omegas, coefficients)
