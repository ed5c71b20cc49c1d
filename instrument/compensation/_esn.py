"""ESN: echo state network regressor of error against measured value (paper §3.3, eqs 30–32).

The calibration curve is a static map (measured value → error), so the reservoir is driven by
a constant input: starting from u(0) = 0 it runs

    u(p+1) = (1 − a)·u(p) + a·tanh(W_in·[1, s·x̃] + W·u(p)),   p = 0 … P−1          (31)

for a fixed number of steps P, with x̃ the measured value scaled to [−1, 1] over the training
range, s the input scaling, a the leak rate and W a sparse random reservoir scaled to spectral
radius ρ < 1 (echo state property). The readout is linear on [u(P), x̃] (eq 32 with f₂ the
identity, since the error is not bounded), fitted by ridge regression with an unpenalised
intercept. Everything random comes from the seed; the weights are stored in ``to_dict``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RESERVOIR_STEPS = 25
CONNECTIONS_PER_NEURON = 10


@dataclass(frozen=True)
class EsnHyperparameters:
    reservoir_size: int
    spectral_radius: float
    leak_rate: float
    input_scaling: float
    ridge: float  # relative to the mean squared feature norm

    def to_dict(self) -> dict:
        return {
            "reservoir_size": int(self.reservoir_size),
            "spectral_radius": float(self.spectral_radius),
            "leak_rate": float(self.leak_rate),
            "input_scaling": float(self.input_scaling),
            "ridge": float(self.ridge),
        }

    @classmethod
    def from_dict(cls, d: dict) -> EsnHyperparameters:
        return cls(int(d["reservoir_size"]), float(d["spectral_radius"]), float(d["leak_rate"]),
                   float(d["input_scaling"]), float(d["ridge"]))


@dataclass(frozen=True)
class Reservoir:
    """Input weights (size, 2) for [bias, input] and sparse reservoir weights (rows, cols, values)."""

    w_in: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    values: np.ndarray

    @property
    def size(self) -> int:
        return self.w_in.shape[0]

    def dense(self) -> np.ndarray:
        w = np.zeros((self.size, self.size))
        w[self.rows, self.cols] = self.values
        return w


def make_reservoir(size: int, spectral_radius: float, seed: int) -> Reservoir:
    """Sparse random reservoir (about ``CONNECTIONS_PER_NEURON`` inputs per neuron) with the given
    spectral radius; input and bias weights uniform in [−1, 1]."""
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
    radius = np.max(np.abs(np.linalg.eigvals(w)))
    values = values * (spectral_radius / radius if radius > 0 else 0.0)
    return Reservoir(w_in, rows, cols, values)


def reservoir_states(reservoir: Reservoir, x_scaled: np.ndarray, leak_rate: float, input_scaling: float,
                     w_dense: np.ndarray | None = None) -> np.ndarray:
    """Reservoir state after ``RESERVOIR_STEPS`` steps of constant input, one row per input."""
    w = reservoir.dense() if w_dense is None else w_dense
    drive = reservoir.w_in[:, 0][None, :] + input_scaling * x_scaled[:, None] * reservoir.w_in[:, 1][None, :]
    u = np.zeros((x_scaled.size, reservoir.size))
    for _ in range(RESERVOIR_STEPS):
        u = (1.0 - leak_rate) * u + leak_rate * np.tanh(drive + u @ w.T)
    return u


def features(reservoir, x_scaled, hp: EsnHyperparameters, w_dense=None) -> np.ndarray:
    return np.hstack([reservoir_states(reservoir, x_scaled, hp.leak_rate, hp.input_scaling, w_dense),
                      x_scaled[:, None]])


def ridge_fit(phi: np.ndarray, y: np.ndarray, ridge: float):
    """Ridge readout with an unpenalised intercept (kernel form, n ≪ features).

    Returns (weights, intercept, in-sample fit, leave-one-out residuals). The leave-one-out
    residuals are exact: r_i / (1 − H_ii) for this linear smoother.
    """
    mean_phi, mean_y = phi.mean(axis=0), y.mean()
    pc, yc = phi - mean_phi, y - mean_y
    gram = pc @ pc.T
    scale = max(np.trace(gram) / y.size, 1e-300)
    d, v = np.linalg.eigh(gram)
    d = np.clip(d, 0.0, None)
    shrink = d / (d + ridge * scale)
    fitted = mean_y + v @ (shrink * (v.T @ yc))
    leverage = 1.0 / y.size + np.einsum("ij,j,ij->i", v, shrink, v)
    loo = (y - fitted) / np.maximum(1.0 - leverage, 1e-12)
    alpha = v @ ((v.T @ yc) / (d + ridge * scale))
    weights = pc.T @ alpha
    return weights, mean_y - mean_phi @ weights, fitted, loo


@dataclass(frozen=True)
class EsnCurve:
    """A trained ESN: error = readout(reservoir(x))."""

    hyper: EsnHyperparameters
    reservoir: Reservoir
    x_lo: float
    x_hi: float
    y_scale: float
    weights: np.ndarray
    intercept: float
    seed: int

    kind = "esn"

    def _scaled(self, x):
        return 2.0 * (np.asarray(x, dtype=float) - self.x_lo) / (self.x_hi - self.x_lo) - 1.0

    def predict(self, x):
        x = np.asarray(x, dtype=float)
        phi = features(self.reservoir, self._scaled(x.ravel()), self.hyper)
        return ((phi @ self.weights + self.intercept) * self.y_scale).reshape(x.shape)

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "hyper": self.hyper.to_dict(),
            "seed": int(self.seed),
            "x_lo": self.x_lo,
            "x_hi": self.x_hi,
            "y_scale": self.y_scale,
            "w_in": self.reservoir.w_in.tolist(),
            "reservoir_rows": self.reservoir.rows.tolist(),
            "reservoir_cols": self.reservoir.cols.tolist(),
            "reservoir_values": self.reservoir.values.tolist(),
            "weights": self.weights.tolist(),
            "intercept": self.intercept,
        }

    @classmethod
    def from_dict(cls, d: dict) -> EsnCurve:
        reservoir = Reservoir(np.asarray(d["w_in"], float), np.asarray(d["reservoir_rows"], int),
                              np.asarray(d["reservoir_cols"], int), np.asarray(d["reservoir_values"], float))
        return cls(EsnHyperparameters.from_dict(d["hyper"]), reservoir, float(d["x_lo"]), float(d["x_hi"]),
                   float(d["y_scale"]), np.asarray(d["weights"], float), float(d["intercept"]), int(d["seed"]))


def fit_esn(x: np.ndarray, y: np.ndarray, hyper: EsnHyperparameters, seed: int = 0,
            reservoir: Reservoir | None = None) -> EsnCurve:
    """Train the readout of a seeded reservoir on (x, y) point means."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    lo, hi = float(x.min()), float(x.max())
    y_scale = float(np.std(y)) or 1.0
    reservoir = reservoir or make_reservoir(hyper.reservoir_size, hyper.spectral_radius, seed)
    xs = 2.0 * (x - lo) / (hi - lo) - 1.0
    weights, intercept, _, _ = ridge_fit(features(reservoir, xs, hyper), y / y_scale, hyper.ridge)
    return EsnCurve(hyper, reservoir, lo, hi, y_scale, weights, float(intercept), seed)


#: PPSO search box: reservoir size, spectral radius, leak rate, log10 input scaling, log10 ridge.
ESN_SEARCH_LOWER = (10, 0.10, 0.05, -1.0, -10.0)
ESN_SEARCH_UPPER = (80, 0.99, 1.00, 1.0, 0.0)


def decode(v: np.ndarray) -> EsnHyperparameters:
    return EsnHyperparameters(int(round(v[0])), float(v[1]), float(v[2]), float(10 ** v[3]), float(10 ** v[4]))


def tune_esn(x: np.ndarray, y: np.ndarray, *, seed: int = 0, n_particles: int = 16, n_iterations: int = 20,
             archive_size: int = 30):
    """PPSO search of the ESN hyper-parameters on two objectives (both in units of std(y)):

    f₁ = in-sample RMS of the fit to the point means (training error);
    f₂ = leave-one-point-out RMS over the interior points (held-out error; the end points stay in
         training because the record never claims values outside the calibrated range).

    ``x, y`` are point means, so leaving one out leaves out a whole calibration point with all
    its repeats. Returns (knee-point hyper-parameters, ParetoResult).
    """
    from instrument.compensation._ppso import ppso_minimize

    x, y = np.asarray(x, float), np.asarray(y, float)
    order = np.argsort(x)
    x, y = x[order], y[order]
    lo, hi = x[0], x[-1]
    xs = 2.0 * (x - lo) / (hi - lo) - 1.0
    ys = y / (float(np.std(y)) or 1.0)
    interior = np.zeros(x.size, dtype=bool)
    interior[1:-1] = True
    unit_reservoirs: dict[int, tuple[Reservoir, np.ndarray]] = {}

    def objectives(v):
        hp = decode(v)
        if hp.reservoir_size not in unit_reservoirs:
            r = make_reservoir(hp.reservoir_size, 0.5, seed)
            unit_reservoirs[hp.reservoir_size] = (r, r.dense() / 0.5)
        r, w_unit = unit_reservoirs[hp.reservoir_size]
        phi = features(r, xs, hp, w_dense=w_unit * hp.spectral_radius)
        _, _, fitted, loo = ridge_fit(phi, ys, hp.ridge)
        return float(np.sqrt(np.mean((ys - fitted) ** 2))), float(np.sqrt(np.mean(loo[interior] ** 2)))

    result = ppso_minimize(objectives, ESN_SEARCH_LOWER, ESN_SEARCH_UPPER, n_particles=n_particles,
                           n_iterations=n_iterations, archive_size=archive_size,
                           integer=(True, False, False, False, False), seed=seed)
    return decode(result.positions[result.knee_index()]), result
