"""Monte Carlo draws of a budget's errors, applied to the measured poses as the physics shares them.

Model (per measured pose j of pose set s, OPR components in M, then the tool transform):

    opr'_sj = opr_sj + ε_sj + δ(v_s) + σ ⊙ opr_sj          tool'_sj = opr'_sj ∘ T_O_E + Δ

ε: POSE terms, independent per pose; δ(v_s): POINT terms, one smooth function of the component
value v_s (the set's barycentre) per draw — sets at the same place share it, sets far apart are
independent; σ: SCALE terms, one relative error per draw times the coordinate; Δ: RUN terms, one
offset per draw on the tool pose. Angles are perturbed as Euler components, as the compensation
corrects them. The perturbation of measured poses stands in for the unknown error of the
measurement (JCGM 101 propagation of distributions; the output distribution's spread is u).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from instrument.uncertainty._budget import BudgetTerm, Correlation, Distribution, UncertaintyBudget
from instrument.uncertainty._rotation import compose


@dataclass(frozen=True)
class PoseSet:
    """Measured poses of one pose set: a point, or one approach direction at a point."""

    label: str
    point: str
    tool: np.ndarray  # (n, 6) measured tool poses in M
    opr: np.ndarray  # (n, 6) the OPR poses they came from

    @property
    def value(self) -> np.ndarray:
        """(6,) barycentre of the OPR components: where the calibration curves are evaluated."""
        centre = self.opr.mean(axis=0)
        angles = self.opr[:, 3:]
        centre[3:] = np.arctan2(np.sin(angles).mean(axis=0), np.cos(angles).mean(axis=0))
        return centre


def unit_draws(distribution: Distribution, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    """Zero-mean, unit-variance draws of the distribution's shape."""
    if distribution is Distribution.RECTANGULAR:
        return rng.uniform(-np.sqrt(3.0), np.sqrt(3.0), size=shape)
    return rng.standard_normal(shape)


def sigma_draws(term: BudgetTerm, draws: int, rng: np.random.Generator) -> np.ndarray:
    """(draws,) multipliers of the term's σ: 1, or √(ν/χ²_ν) for an estimate with ν dof."""
    if np.isinf(term.dof):
        return np.ones(draws)
    return np.sqrt(term.dof / rng.chisquare(term.dof, size=draws))


def _sqrt_psd(matrix: np.ndarray) -> np.ndarray:
    """A square root L with L·Lᵀ = matrix, for positive semi-definite (even singular) matrices."""
    eigenvalues, vectors = np.linalg.eigh(matrix)
    return vectors * np.sqrt(np.clip(eigenvalues, 0.0, None))


def _point_correlation(term: BudgetTerm, sets: Sequence[PoseSet], values: np.ndarray, k: int) -> np.ndarray:
    length = None if term.correlation_length is None else term.correlation_length[k]
    if length is None:
        points = np.array([s.point for s in sets])
        return (points[:, None] == points[None, :]).astype(float)
    difference = values[:, None, k] - values[None, :, k]
    return np.exp(-0.5 * (difference / length) ** 2)


def perturbed_tools(
    sets: Sequence[PoseSet],
    budget: UncertaintyBudget,
    transform: tuple[np.ndarray, np.ndarray] | None,
    draws: int,
    rng: np.random.Generator,
) -> dict[str, np.ndarray]:
    """(draws, n, 6) perturbed tool poses per set label."""
    from scipy import special
    opr_delta = {s.label: np.zeros((draws, *s.opr.shape)) for s in sets}
    tool_delta = np.zeros((draws, 1, 6))
    values = np.array([s.value for s in sets])
    for term in budget.terms:
        if not term.active:
            continue
        u = np.array(term.standard_uncertainty)
        spread = sigma_draws(term, draws, rng)
        if term.correlation is Correlation.POSE:
            for s in sets:
                opr_delta[s.label] += unit_draws(term.distribution, opr_delta[s.label].shape, rng) * u * spread[:, None,
                                                                                                                None]
        elif term.correlation is Correlation.POINT:
            u_at = term.uncertainty_at(values)  # (n_sets, 6)
            for k in np.flatnonzero(u > 0):
                root = _sqrt_psd(_point_correlation(term, sets, values, int(k)))
                z = rng.standard_normal((draws, len(sets))) @ root.T  # unit variance, correlated as the curve
                if term.distribution is Distribution.RECTANGULAR:
                    z = np.sqrt(3.0) * (2.0 * special.ndtr(z) - 1.0)
                delta = z * u_at[:, k] * spread[:, None]
                for index, s in enumerate(sets):
                    opr_delta[s.label][:, :, k] += delta[:, index, None]
        elif term.correlation is Correlation.SCALE:
            shape = (draws, 1) if term.shared else (draws, 6)
            relative = unit_draws(term.distribution, shape, rng) * u * spread[:, None]
            for s in sets:
                opr_delta[s.label] += relative[:, None, :] * s.opr[None]
        else:  # RUN
            shape = (draws, 1) if term.shared else (draws, 6)
            tool_delta += (unit_draws(term.distribution, shape, rng) * u * spread[:, None])[:, None, :]
    out = {}
    for s in sets:
        opr = s.opr[None] + opr_delta[s.label]
        tool = opr if transform is None else compose(opr, *transform)
        out[s.label] = tool + tool_delta
    return out
