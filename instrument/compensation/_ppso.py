"""PPSO: Pareto (multi-objective) particle swarm optimisation (paper §3.2, eqs 24–29).

- Non-dominated solutions found so far are kept in an archive E of fixed capacity |E|.
- The archive's objective space is cut into a grid; a member's density h_j is the number of
  archive members in its cell. When the archive overflows, members leave the densest cell.
- Each particle F_i takes as guide (its "population best") the archive member E_j maximising

      Fit(i, j) = τ_t · max_j(Δδ_ij) / Δδ_ij + (1 − τ_t) · max_j(h_j) / h_j        (24)
      τ_t = m_t / |E|                                                              (25)
      Δδ_ij = |Sigma(F_i) − Sigma(E_j)| + ε                                         (28)
      Sigma(F) = ((K₂f₁)² − (K₁f₂)²) / ((K₂f₁)² + (K₁f₂)²)                           (29)

  so a sparse archive (small τ) steers particles to empty cells (global search) and a full one
  steers each particle to the member with the nearest Sigma value (local search). K₁, K₂ are the
  largest objective values; objectives are shifted by their current minimum first so Sigma is
  defined for any sign (identical to eq 29 when the minima are 0).
- Velocity update with inertia falling linearly, cognitive/social terms, and a mutation
  (turbulence) whose reach shrinks with the iterations; positions stay inside the bounds.

Seeded and deterministic: one ``numpy.random.Generator`` drives every random choice.
Two objectives, both minimised.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np


def dominates(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.all(a <= b) and np.any(a < b))


def non_dominated_mask(objectives: np.ndarray) -> np.ndarray:
    """True for rows not dominated by any other row (duplicates: the first one is kept)."""
    f = np.asarray(objectives, dtype=float)
    n = f.shape[0]
    # dominated[i, j]: row j dominates row i
    no_worse = np.all(f[None, :, :] <= f[:, None, :], axis=2)
    better = np.any(f[None, :, :] < f[:, None, :], axis=2)
    dominated = np.any(no_worse & better, axis=1)
    same = np.all(f[None, :, :] == f[:, None, :], axis=2)
    earlier_duplicate = np.any(np.tril(same, k=-1), axis=1)
    return ~(dominated | earlier_duplicate) if n else np.zeros(0, dtype=bool)


def sigma_values(f: np.ndarray, f_min: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Sigma of eq 29 for each row of shifted objectives (f − f_min), with K = max shifted values."""
    s = np.clip(f - f_min, 0.0, None)
    a = (k[1] * s[:, 0]) ** 2
    b = (k[0] * s[:, 1]) ** 2
    den = a + b
    return np.where(den > 0, (a - b) / np.where(den > 0, den, 1.0), 0.0)


def grid_density(f: np.ndarray, divisions: int) -> np.ndarray:
    """Number of archive members in each member's grid cell."""
    lo, hi = f.min(axis=0), f.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    cells = np.minimum(((f - lo) / span * divisions).astype(int), divisions - 1)
    cell = cells[:, 0] * divisions + cells[:, 1]  # one integer per cell of the 2-D grid
    return np.bincount(cell, minlength=divisions * divisions)[cell]


@dataclass(frozen=True)
class ParetoResult:
    """Final Pareto archive.

    Attributes
    ----------
    positions : (k, d) decision vectors of the archive, sorted by the first objective
    objectives : (k, 2) objective values
    n_evaluations : int
    """

    positions: np.ndarray
    objectives: np.ndarray
    n_evaluations: int

    def ideal_point_index(self) -> int:
        """Index of the member nearest to the ideal point (min f₁, min f₂), distances in the
        objectives' own units: sound when both objectives measure the same quantity in one unit."""
        f = self.objectives
        return int(np.argmin(np.sum((f - f.min(axis=0)) ** 2, axis=1)))

    def knee_index(self) -> int:
        """Index of the knee: the front point farthest from the line through the two extremes
        (objectives normalised to [0, 1]); with fewer than 3 points, the lowest second objective.

        Normalising makes an objective that barely varies as important as one spanning decades;
        prefer ``ideal_point_index`` when both objectives share a unit."""
        f = self.objectives
        if f.shape[0] < 3:
            return int(np.argmin(f[:, 1]))
        lo, hi = f.min(axis=0), f.max(axis=0)
        g = (f - lo) / np.where(hi > lo, hi - lo, 1.0)
        a, b = g[np.argmin(g[:, 0])], g[np.argmin(g[:, 1])]
        direction = b - a
        norm = np.linalg.norm(direction)
        if norm == 0:
            return int(np.argmin(f[:, 1]))
        distance = np.abs(direction[0] * (g[:, 1] - a[1]) - direction[1] * (g[:, 0] - a[0])) / norm
        return int(np.argmax(distance))


def _truncate(pos, obj, capacity, divisions, rng):
    while obj.shape[0] > capacity:
        density = grid_density(obj, divisions)
        crowded = np.flatnonzero(density == density.max())
        drop = rng.choice(crowded)
        pos, obj = np.delete(pos, drop, axis=0), np.delete(obj, drop, axis=0)
    return pos, obj


def _update_archive(arch_pos, arch_obj, new_pos, new_obj, capacity, divisions, rng):
    pos = np.vstack([arch_pos, new_pos]) if arch_pos.size else new_pos
    obj = np.vstack([arch_obj, new_obj]) if arch_obj.size else new_obj
    keep = non_dominated_mask(obj)
    return _truncate(pos[keep], obj[keep], capacity, divisions, rng)


def ppso_minimize(
    objectives: Callable[[np.ndarray], Sequence[float] | np.ndarray],
    lower: Sequence[float],
    upper: Sequence[float],
    *,
    n_particles: int = 30,
    n_iterations: int = 100,
    archive_size: int = 50,
    grid_divisions: int = 10,
    inertia: tuple[float, float] = (0.5, 0.3),
    cognitive: float = 1.0,
    social: float = 2.0,
    mutation_rate: float = 0.5,
    integer: Sequence[bool] | None = None,
    epsilon: float = 1e-9,
    seed: int = 0,
    initial: np.ndarray | None = None,
    vectorized: bool = False,
) -> ParetoResult:
    """Minimise two objectives with the Pareto PSO of the paper (eqs 24–29).

    Parameters
    ----------
    objectives : callable(x (d,)) → (f1, f2); with ``vectorized``, callable(x (k, d)) → (k, 2) for
        the whole swarm at once
    lower, upper : bounds of the decision vector
    integer : per-dimension flag; flagged dimensions are rounded before evaluation
    seed : all randomness comes from ``numpy.random.default_rng(seed)``
    initial : (k, d) positions that replace the first k random particles (a warm start)
    vectorized : ``objectives`` scores every particle of an iteration in one call (same result)

    Returns
    -------
    ParetoResult
    """
    rng = np.random.default_rng(seed)
    low, high = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    if low.shape != high.shape or np.any(high <= low):
        raise ValueError("PPSO bounds: lower and upper must have one shape and lower < upper")
    d = low.size
    span = high - low
    is_int = np.zeros(d, dtype=bool) if integer is None else np.asarray(integer, dtype=bool)
    n_eval = 0

    def evaluate(x):
        nonlocal n_eval
        x = np.where(is_int, np.round(x), x)
        if vectorized:
            out = np.asarray(objectives(x), dtype=float).reshape(x.shape[0], -1)[:, :2]
            n_eval += x.shape[0]
        else:
            out = np.empty((x.shape[0], 2))
            for i, xi in enumerate(x):
                out[i] = np.asarray(objectives(xi), dtype=float)[:2]
                n_eval += 1
        return np.where(np.isfinite(out), out, np.inf), x

    pos = low + rng.random((n_particles, d)) * span
    if initial is not None:
        start = np.clip(np.atleast_2d(np.asarray(initial, dtype=float))[:n_particles], low, high)
        pos[: start.shape[0]] = start
    vel = np.zeros_like(pos)
    obj, pos = evaluate(pos)
    best_pos, best_obj = pos.copy(), obj.copy()
    finite = np.all(np.isfinite(obj), axis=1)
    arch_pos, arch_obj = _update_archive(np.empty((0, d)), np.empty((0, 2)), pos[finite], obj[finite],
                                         archive_size, grid_divisions, rng)

    for t in range(n_iterations):
        progress = t / max(n_iterations - 1, 1)
        w = inertia[0] + (inertia[1] - inertia[0]) * progress
        # guide selection (eqs 24–29)
        if arch_obj.shape[0] == 0:
            guides = best_pos
        else:
            everything = np.vstack([arch_obj, obj[np.all(np.isfinite(obj), axis=1)]])
            f_min = everything.min(axis=0)
            k = np.maximum(everything.max(axis=0) - f_min, 1e-300)
            sig_arch = sigma_values(arch_obj, f_min, k)
            sig_part = sigma_values(np.where(np.isfinite(obj), obj, everything.max(axis=0)), f_min, k)
            h = grid_density(arch_obj, grid_divisions).astype(float)
            tau = arch_obj.shape[0] / archive_size
            delta = np.abs(sig_part[:, None] - sig_arch[None, :]) + epsilon
            fit = tau * delta.max(axis=1, keepdims=True) / delta + (1 - tau) * h.max() / h[None, :]
            # ties (common when τ is small) are broken at random, not by archive order
            fit = fit + 1e-12 * rng.random(fit.shape)
            guides = arch_pos[np.argmax(fit, axis=1)]
        r1, r2 = rng.random((2, n_particles, d))
        vel = w * vel + cognitive * r1 * (best_pos - pos) + social * r2 * (guides - pos)
        vel = np.clip(vel, -span, span)
        pos = pos + vel
        # mutation with reach shrinking over the run (Coello, Pulido & Lechuga 2004)
        reach = (1.0 - progress) ** (1.0 / mutation_rate)
        mutate = rng.random(n_particles) < reach
        for mutant in np.flatnonzero(mutate):
            j = int(rng.integers(d))
            pos[mutant, j] += reach * span[j] * (rng.random() - 0.5)
        out = (pos < low) | (pos > high)
        vel[out] *= -1.0
        pos = np.clip(pos, low, high)
        obj, pos = evaluate(pos)
        # personal best: replace when dominated; when neither dominates, take the new one half the time
        for i in range(n_particles):
            if dominates(obj[i], best_obj[i]) or (
                not dominates(best_obj[i], obj[i]) and rng.random() < 0.5
            ):
                best_pos[i], best_obj[i] = pos[i], obj[i]
        finite = np.all(np.isfinite(obj), axis=1)
        arch_pos, arch_obj = _update_archive(arch_pos, arch_obj, pos[finite], obj[finite],
                                             archive_size, grid_divisions, rng)
    order = np.argsort(arch_obj[:, 0])
    return ParetoResult(arch_pos[order], arch_obj[order], n_eval)


def generational_distance(front: np.ndarray, reference_front: np.ndarray) -> float:
    """GD = sqrt(Σ d_i²) / n: d_i is the distance of each found point to the nearest point of a
    densely sampled true front (Van Veldhuizen & Lamont 1998)."""
    front, reference_front = np.atleast_2d(front), np.atleast_2d(reference_front)
    d = np.sqrt(((front[:, None, :] - reference_front[None, :, :]) ** 2).sum(axis=2)).min(axis=1)
    return float(np.sqrt(np.sum(d**2)) / front.shape[0])
