"""CSF-PPSO-ESN: the PPSO search of the joint CSF + ESN model's hyper-parameters (paper §3.2–3.4).

The model (``instrument.compensation._esn``) is a linear smoother for fixed hyper-parameters, so
each candidate's leave-one-point-out residuals are exact in closed form. PPSO searches (size, ρ,
leak, s_in, μ, λ) on f₁ = training RMS and f₂ = leave-one-point-out RMS over the interior points;
both are RMS of the same quantity in the same unit, so the model is chosen in that unit
(``SELECTIONS``; default: the one-standard-error rule over every model the swarm evaluated), never
after normalising each objective to [0, 1].

Before the swarm starts, the ripple search (``instrument.compensation._ripple``) decides which
periodic terms the spline part carries (none on smooth data); the swarm starts with one particle
at that CSF + ripple alone (ridge at its upper bound, so the ESN is all but off), so the search
always holds a model as good as it. The whole swarm is scored in one batched evaluation per
iteration (reservoirs padded to the largest size with silent neurons: exact).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from instrument.compensation._esn import (
    RESERVOIR_STEPS,
    CsfEsnCurve,
    EsnHyperparameters,
    JointFit,
    Reservoir,
    features,
    joint_fit,
    make_reservoir,
)
from instrument.compensation._ppso import ParetoResult, ppso_minimize
from instrument.compensation._ripple import find_ripples
from instrument.compensation._spline import PartialSpline, curvature_column, ripple_columns, smooth

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


#: PPSO search box: reservoir size, spectral radius, leak rate, log10 input scaling, log10 ridge μ,
#: log10 smoothing λ.
SEARCH_LOWER = (10.0, 0.10, 0.05, -1.0, -8.0, -9.0)
SEARCH_UPPER = (60.0, 0.99, 1.00, 1.0, 4.0, 3.0)


def decode(v: np.ndarray) -> EsnHyperparameters:
    """Hyper-parameters from a PPSO position."""
    return EsnHyperparameters(int(round(v[0])), float(v[1]), float(v[2]), float(10 ** v[3]), float(10 ** v[4]),
                              float(10 ** v[5]))


def _tanh(x: np.ndarray) -> np.ndarray:
    """tanh in place as 1 − 2/(e^{2x} + 1): a third of ``np.tanh``'s time here, within 4e-16 of it (the
    swarm evaluates 25 reservoir steps for every candidate; ``features`` keeps ``np.tanh``)."""
    with np.errstate(over="ignore"):  # e^{2x} = inf gives exactly 1
        np.multiply(x, 2.0, out=x)
        np.exp(x, out=x)
    x += 1.0
    np.divide(-2.0, x, out=x)
    x += 1.0
    return x


@dataclass(frozen=True)
class CsfEsnProblem:
    """Scaled point means and the cached pieces every PPSO evaluation reuses.

    ``omegas`` are the ripples the spline part carries (angular frequencies in u; empty: none).
    """

    u: np.ndarray
    y: np.ndarray
    w: np.ndarray
    spline: PartialSpline
    seed: int
    center: float
    half_span: float
    y_scale: float
    omegas: np.ndarray

    @classmethod
    def from_points(cls, x: np.ndarray, y: np.ndarray, w: np.ndarray, seed: int,
                    omegas: np.ndarray | None = None) -> CsfEsnProblem:
        order = np.argsort(x)
        x, y, w = (np.asarray(a, float)[order] for a in (x, y, w))
        center, half_span = 0.5 * (x[0] + x[-1]), 0.5 * (x[-1] - x[0])
        y_scale = float(np.std(y)) or 1.0
        u = (x - center) / half_span
        omegas = np.zeros(0) if omegas is None else np.asarray(omegas, float)
        columns = np.hstack([curvature_column(u)[:, None], ripple_columns(u, omegas)])
        return cls(u, y / y_scale, w, PartialSpline(u, w, columns), seed, float(center), float(half_span), y_scale,
                   omegas)

    def with_ripples(self, omegas: np.ndarray) -> CsfEsnProblem:
        """The same points with these ripples in the spline part."""
        x = self.center + self.half_span * self.u
        return CsfEsnProblem.from_points(x, self.y * self.y_scale, self.w, self.seed, omegas)

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
                           fitted.spline_values, fitted.curvature, fitted.weights, self.seed, self.omegas,
                           fitted.ripple_coefficients)

    def swarm_hats(self, positions: np.ndarray) -> np.ndarray:
        """Hat matrices (k, n, n) of the joint fits of k PPSO positions, all at once.

        The reservoirs are padded to the largest size with silent neurons (no input, no
        connections: their state stays 0), so every fit equals ``fit(decode(v)).hat``.
        """
        hypers = [decode(v) for v in positions]
        k, n, largest = len(hypers), self.u.size, max(h.reservoir_size for h in hypers)
        w_in = np.zeros((k, largest, 2))
        w_t = np.zeros((k, largest, largest))
        for i, h in enumerate(hypers):
            r = self.reservoir(h.reservoir_size)
            w_in[i, : r.size] = r.w_in
            w_t[i, r.cols, r.rows] = r.values / 0.5 * h.spectral_radius  # transposed: state @ Wᵀ
        scaling, leak, ridge, lam = (np.array([getattr(h, a) for h in hypers])
                                     for a in ("input_scaling", "leak_rate", "ridge", "smoothing"))
        drive = w_in[:, None, :, 0] + (scaling[:, None, None] * self.u[None, :, None]) * w_in[:, None, :, 1]
        keep, leak = (1.0 - leak)[:, None, None], leak[:, None, None]
        state = leak * _tanh(drive.copy())  # as ``features``: the first step from rest
        for _ in range(RESERVOIR_STEPS - 1):
            update = _tanh(np.add(drive, state @ w_t))
            state *= keep
            update *= leak
            state += update
        phi = np.concatenate([state, np.broadcast_to(self.u[None, :, None], (k, n, 1))], axis=2)
        gram = phi @ np.swapaxes(phi, 1, 2)
        spline_hat, _ = self.spline.smoothers(lam)
        eye = np.eye(n)
        m = self.spline.w[None, :, None] * (eye[None] - spline_hat)
        mu = ridge * np.maximum(np.trace(gram, axis1=1, axis2=2) / n, 1e-300)
        q = np.linalg.solve(m @ gram + mu[:, None, None] * eye[None], m)
        return spline_hat + (eye[None] - spline_hat) @ (gram @ q)


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
                 n_iterations: int = 15, archive_size: int = 30, selection: str = "one_se",
                 noise_variance: float | None = None, ripples: bool = True) -> Tuning:
    """PPSO search of the CSF-ESN hyper-parameters on aligned point means, then the chosen fit.

    Parameters
    ----------
    x, y, w : (n,) point means (measured value, error) and repeat counts; n ≥ 4
    seed : seeds the reservoirs and the swarm
    n_particles, n_iterations, archive_size : PPSO budget
    selection : one of ``SELECTIONS``
    noise_variance : variance of one observation (the noise floor squared), or None; guards the
        ripple search
    ripples : search for ripples first (False: the spline part carries none, as before issue 25)

    Returns
    -------
    Tuning

    Notes
    -----
    The swarm starts with one particle at the CSF alone with its ripples (λ from the ripple
    search, or by GCV when it kept none; ridge at its upper bound, so the ESN is all but switched
    off): the search always holds a model as good as that CSF.
    """
    if selection not in SELECTIONS:
        raise ValueError(f"selection must be one of {SELECTIONS}, got {selection!r}")
    problem = CsfEsnProblem.from_points(x, y, w, seed)
    csf_lam = smooth(problem.u, problem.y, problem.w, "gcv", end_curvature=True).lam
    if ripples:
        search = find_ripples(problem.u, problem.y, problem.w,
                              noise_variance=None if noise_variance is None else noise_variance / problem.y_scale**2)
        if search.omegas.size:
            problem, csf_lam = problem.with_ripples(search.omegas), search.lam
    interior = _interior(problem.u.size)
    records: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []

    def objectives(positions: np.ndarray) -> np.ndarray:
        hats = problem.swarm_hats(positions)
        fitted = hats @ problem.y
        loo = (problem.y[None] - fitted) / np.maximum(1.0 - np.einsum("kii->ki", hats), 1e-12)
        squares = loo[:, interior] ** 2
        train_rms = np.sqrt(np.sum(problem.w * (problem.y[None] - fitted) ** 2, axis=1) / np.sum(problem.w))
        heldout_rms = np.sqrt(np.mean(squares, axis=1))
        records.append((np.array(positions, dtype=float), train_rms, heldout_rms, np.trace(hats, axis1=1, axis2=2),
                        squares))
        return np.column_stack([train_rms, heldout_rms])

    log_lam = float(np.clip(np.log10(csf_lam), SEARCH_LOWER[5], SEARCH_UPPER[5]))
    start = np.array([[30.0, 0.8, 0.5, 0.0, SEARCH_UPPER[4], log_lam]])
    front = ppso_minimize(objectives, SEARCH_LOWER, SEARCH_UPPER, n_particles=n_particles, n_iterations=n_iterations,
                          archive_size=archive_size, integer=(True, False, False, False, False, False), seed=seed,
                          initial=start, vectorized=True)
    positions, train, heldout, dof, squares = (np.concatenate([r[i] for r in records]) for i in range(5))
    ok = np.isfinite(train) & np.isfinite(heldout)
    log = SwarmLog(positions[ok], train[ok], heldout[ok], dof[ok], squares[ok])
    position = select(front, log, selection)
    hyper = decode(position)
    at = int(np.flatnonzero(np.all(log.positions == position, axis=1))[0])
    return Tuning(problem.curve(hyper), front, log, float(log.train[at] * problem.y_scale),
                  float(log.heldout[at] * problem.y_scale), float(log.dof[at]))
