"""CSF-PPSO-ESN: smoothing spline plus echo state network, tuned by PPSO (paper §3.2–3.4).

The paper's step 4 lets the PPSO-tuned ESN improve "on the basis of" the CSF. Here both are one
model, fitted jointly to the aligned point means (u = measured value scaled to [−1, 1], y = error
scaled to unit spread, w = repeat counts):

    y ≈ s(u) + c·u² + Φ(u)·b,   minimising Σ w (y − fit)² + λ·∫ s''² + μ·|b|²

- s is the natural cubic spline through its knot values (the CSF, eqs 18–23); c·u² is unpenalised,
  so the curvature at the ends is fitted instead of forced to zero (natural end conditions);
- Φ(u) are the ESN's features (eqs 30–32): a static map needs a constant input, so the leaky tanh
  reservoir (sparse, ``CONNECTIONS_PER_NEURON`` inputs per neuron, spectral radius ρ < 1) runs
  ``RESERVOIR_STEPS`` steps from rest with input [1, s_in·u]; its final state and u are the
  features, b the linear readout (eq 32 with f₂ the identity: the error is not bounded).

For fixed hyper-parameters the fit is a linear smoother, fitted = A·y, so the leave-one-point-out
residuals are exact in closed form: r_i / (1 − A_ii) (removing a point's weight equals refitting
without it: the natural spline through the other points is also the optimum with the knot kept).
PPSO searches (size, ρ, leak, s_in, μ, λ) on f₁ = training RMS and f₂ = leave-one-point-out RMS
over the interior points; both are RMS of the same quantity in the same unit, so the model is
chosen in that unit (``SELECTIONS``; default: the one-standard-error rule over every model the
swarm evaluated), never after normalising each objective to [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from instrument.compensation._ppso import ParetoResult, ppso_minimize
from instrument.compensation._spline import PartialSpline, curvature_column, natural_spline_basis, smooth

RESERVOIR_STEPS = 25
CONNECTIONS_PER_NEURON = 10

#: How the model is chosen from what the swarm found:
#: "one_se": Breiman's one-standard-error rule over every model the swarm evaluated: the one with the
#:     fewest effective degrees of freedom (trace of the hat matrix) whose held-out RMS is within one
#:     standard error of the lowest (the standard error from the scatter of that model's per-point
#:     squared held-out residuals). On the (training, held-out) front itself the rule is void: a
#:     smoother model has a higher training error, so it is dominated unless it also predicts better;
#: "ideal_point": the front member nearest to (min f₁, min f₂) in the objectives' own unit;
#: "min_heldout": the front member with the lowest held-out RMS;
#: "knee": the paper-era knee (farthest from the chord after normalising both objectives to [0, 1]);
#:     kept for comparison. Unsound in principle (normalising weighs a training RMS that barely
#:     varies like a held-out RMS spanning decades); on the paper-era ESN alone it picked
#:     over-fitted networks, on the joint model it happens to land near the others.
SELECTIONS = ("one_se", "ideal_point", "min_heldout", "knee")


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
    """The joint smoother for fixed hyper-parameters: hat matrix and the parameters for y."""

    hat: np.ndarray
    spline_values: np.ndarray
    curvature: float
    weights: np.ndarray

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
    return JointFit(hat, theta[:n], float(theta[n]), weights)


@dataclass(frozen=True)
class CsfEsnCurve:
    """A trained CSF-ESN curve: error = y_scale·(s(u) + c·u² + Φ(u)·b), u = (x − center)/half_span."""

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

    kind = "csf-esn"

    def predict(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        u = ((x - self.center) / self.half_span).ravel()
        lo, hi = float(self.knots_u[0]), float(self.knots_u[-1])
        fit = (natural_spline_basis(self.knots_u, u) @ self.spline_values
               + self.curvature * curvature_column(u, lo, hi) + features(self.reservoir, u, self.hyper) @ self.weights)
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
        }

    @classmethod
    def from_dict(cls, d: dict) -> CsfEsnCurve:
        reservoir = Reservoir(np.asarray(d["w_in"], float), np.asarray(d["reservoir_rows"], int),
                              np.asarray(d["reservoir_cols"], int), np.asarray(d["reservoir_values"], float))
        return cls(EsnHyperparameters.from_dict(d["hyper"]), reservoir, float(d["center"]), float(d["half_span"]),
                   float(d["y_scale"]), np.asarray(d["knots_u"], float), np.asarray(d["spline_values"], float),
                   float(d["curvature"]), np.asarray(d["weights"], float), int(d["seed"]))


#: PPSO search box: reservoir size, spectral radius, leak rate, log10 input scaling, log10 ridge μ,
#: log10 smoothing λ.
SEARCH_LOWER = (10.0, 0.10, 0.05, -1.0, -8.0, -9.0)
SEARCH_UPPER = (60.0, 0.99, 1.00, 1.0, 4.0, 3.0)


def decode(v: np.ndarray) -> EsnHyperparameters:
    """Hyper-parameters from a PPSO position."""
    return EsnHyperparameters(int(round(v[0])), float(v[1]), float(v[2]), float(10 ** v[3]), float(10 ** v[4]),
                              float(10 ** v[5]))


@dataclass(frozen=True)
class CsfEsnProblem:
    """Scaled point means and the cached pieces every PPSO evaluation reuses."""

    u: np.ndarray
    y: np.ndarray
    w: np.ndarray
    spline: PartialSpline
    seed: int
    center: float
    half_span: float
    y_scale: float

    @classmethod
    def from_points(cls, x: np.ndarray, y: np.ndarray, w: np.ndarray, seed: int) -> CsfEsnProblem:
        order = np.argsort(x)
        x, y, w = (np.asarray(a, float)[order] for a in (x, y, w))
        center, half_span = 0.5 * (x[0] + x[-1]), 0.5 * (x[-1] - x[0])
        y_scale = float(np.std(y)) or 1.0
        u = (x - center) / half_span
        return cls(u, y / y_scale, w, PartialSpline(u, w), seed, float(center), float(half_span), y_scale)

    def reservoir(self, size: int) -> Reservoir:
        return make_reservoir(size, 0.5, self.seed)

    def fit(self, hyper: EsnHyperparameters, reservoir: Reservoir | None = None,
            unit_dense: np.ndarray | None = None, parameters: bool = True) -> JointFit:
        """Joint fit for these hyper-parameters (``unit_dense``: the reservoir's dense weights at ρ = 1)."""
        reservoir = reservoir or self.reservoir(hyper.reservoir_size)
        unit = reservoir.dense() / 0.5 if unit_dense is None else unit_dense
        phi = features(reservoir, self.u, hyper, w_dense=unit * hyper.spectral_radius)
        return joint_fit(self.spline, self.y, phi, hyper, parameters)

    def curve(self, hyper: EsnHyperparameters) -> CsfEsnCurve:
        """The trained curve in SI units (the reservoir stored at its real spectral radius)."""
        base = self.reservoir(hyper.reservoir_size)
        fitted = self.fit(hyper, base)
        reservoir = Reservoir(base.w_in, base.rows, base.cols, base.values / 0.5 * hyper.spectral_radius)
        return CsfEsnCurve(hyper, reservoir, self.center, self.half_span, self.y_scale, self.u,
                           fitted.spline_values, fitted.curvature, fitted.weights, self.seed)


def _interior(n: int) -> np.ndarray:
    mask = np.zeros(n, dtype=bool)
    mask[1:-1] = True
    return mask


@dataclass(frozen=True)
class SwarmLog:
    """Every model the swarm evaluated.

    Attributes
    ----------
    positions : (k, 6) PPSO positions (see ``decode``)
    train, heldout : (k,) training and leave-one-point-out RMS (units of the error's spread)
    dof : (k,) effective degrees of freedom (trace of the hat matrix)
    squares : (k, m) squared leave-one-point-out residuals of the m interior points
    """

    positions: np.ndarray
    train: np.ndarray
    heldout: np.ndarray
    dof: np.ndarray
    squares: np.ndarray


def select(front: ParetoResult, log: SwarmLog, selection: str) -> np.ndarray:
    """Position of the chosen model (see ``SELECTIONS``).

    Parameters
    ----------
    front : ParetoResult
        f₁ = training RMS, f₂ = held-out RMS, in one unit.
    log : SwarmLog of every evaluation (used by "one_se")
    selection : str

    Returns
    -------
    (6,) position
    """
    f = front.objectives
    if selection == "knee":
        return front.positions[front.knee_index()]
    if selection == "min_heldout":
        return front.positions[int(np.argmin(f[:, 1]))]
    if selection == "ideal_point":
        return front.positions[front.ideal_point_index()]
    if selection == "one_se":
        best = int(np.argmin(log.heldout))
        squares = log.squares[best]
        se = float(np.std(squares, ddof=1) / np.sqrt(squares.size)) / (2.0 * max(float(log.heldout[best]), 1e-300))
        within = np.flatnonzero(log.heldout <= log.heldout[best] + se)
        return log.positions[within[np.lexsort((log.heldout[within], log.dof[within]))[0]]]
    raise ValueError(f"selection must be one of {SELECTIONS}, got {selection!r}")


@dataclass(frozen=True)
class Tuning:
    """What ``tune_csf_esn`` found: the curve, the Pareto front, the log of every evaluation and the
    chosen model's figures (training and held-out RMS in SI units, effective dof)."""

    curve: CsfEsnCurve
    front: ParetoResult
    log: SwarmLog
    train_rms: float
    heldout_rms: float
    dof: float


def tune_csf_esn(x: np.ndarray, y: np.ndarray, w: np.ndarray, *, seed: int = 0, n_particles: int = 12,
                 n_iterations: int = 15, archive_size: int = 30, selection: str = "one_se") -> Tuning:
    """PPSO search of the CSF-ESN hyper-parameters on aligned point means, then the chosen fit.

    Parameters
    ----------
    x, y, w : (n,) point means (measured value, error) and repeat counts; n ≥ 4
    seed : seeds the reservoirs and the swarm
    n_particles, n_iterations, archive_size : PPSO budget
    selection : one of ``SELECTIONS``

    Returns
    -------
    Tuning

    Notes
    -----
    The swarm starts with one particle at the CSF alone (λ by GCV, ridge at its upper bound, so
    the ESN is all but switched off): the search always holds a model as good as the CSF.
    """
    if selection not in SELECTIONS:
        raise ValueError(f"selection must be one of {SELECTIONS}, got {selection!r}")
    problem = CsfEsnProblem.from_points(x, y, w, seed)
    interior = _interior(problem.u.size)
    unit_reservoirs: dict[int, tuple[Reservoir, np.ndarray]] = {}
    records: list[tuple[np.ndarray, float, float, float, np.ndarray]] = []

    def objectives(v: np.ndarray) -> tuple[float, float]:
        hyper = decode(v)
        if hyper.reservoir_size not in unit_reservoirs:
            r = problem.reservoir(hyper.reservoir_size)
            unit_reservoirs[hyper.reservoir_size] = (r, r.dense() / 0.5)
        r, unit = unit_reservoirs[hyper.reservoir_size]
        fitted = problem.fit(hyper, r, unit, parameters=False)
        squares = fitted.loo_residuals(problem.y)[interior] ** 2
        train = problem.y - fitted.hat @ problem.y
        train_rms = float(np.sqrt(np.sum(problem.w * train**2) / np.sum(problem.w)))
        heldout_rms = float(np.sqrt(np.mean(squares)))
        records.append((np.array(v, dtype=float), train_rms, heldout_rms, float(np.trace(fitted.hat)), squares))
        return train_rms, heldout_rms

    csf_lam = smooth(problem.u, problem.y, problem.w, "gcv", end_curvature=True).lam
    log_lam = float(np.clip(np.log10(csf_lam), SEARCH_LOWER[5], SEARCH_UPPER[5]))
    start = np.array([[30.0, 0.8, 0.5, 0.0, SEARCH_UPPER[4], log_lam]])
    front = ppso_minimize(objectives, SEARCH_LOWER, SEARCH_UPPER, n_particles=n_particles, n_iterations=n_iterations,
                          archive_size=archive_size, integer=(True, False, False, False, False, False), seed=seed,
                          initial=start)
    ok = [r for r in records if np.isfinite(r[1]) and np.isfinite(r[2])]
    log = SwarmLog(np.array([r[0] for r in ok]), np.array([r[1] for r in ok]), np.array([r[2] for r in ok]),
                   np.array([r[3] for r in ok]), np.array([r[4] for r in ok]))
    position = select(front, log, selection)
    hyper = decode(position)
    at = int(np.flatnonzero(np.all(log.positions == position, axis=1))[0])
    return Tuning(problem.curve(hyper), front, log, float(log.train[at] * problem.y_scale),
                  float(log.heldout[at] * problem.y_scale), float(log.dof[at]))
