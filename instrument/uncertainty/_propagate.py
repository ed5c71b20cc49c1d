"""Uncertainty of every ISO 9283 figure of a run: Monte Carlo through the real formulas.

``iso_uncertainty`` draws the budget's errors (``_sampling``), applies them to the measured poses,
recomputes every figure with ``instrument.iso9283`` and summarises each figure's distribution:

- the estimate, u and U from the draws (``_summary``): the draws' mean shift is the measured
  value's noise bias (adding the errors once more moves a figure as the errors moved it in the
  first place), so one extrapolation step back removes it — linearly for signed figures, in the
  square for spreads and distances, where noise adds variance (SIMEX, Cook & Stefanski 1994).
  The corrected value is the estimate (GUM 3.2.4: correct recognised systematic effects), U = k·u
  with k = 2; with ``correct_bias=False`` the value stays the ISO formula's and the bias is
  carried in U instead: U = k·u + |bias| (GUM F.2.4.5);
- per-term contributions: u of the figure with that term alone (a separate, smaller Monte Carlo);
- the 25 % rule: U ≤ 0.25 × the characteristic (the figure's own magnitude, or a caller's value
  such as the robot's specified RP), flagged per figure.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from instrument.iso9283 import ISO9283Error
from instrument.uncertainty._budget import COMPONENTS, Correlation, UncertaintyBudget
from instrument.uncertainty._errors import UncertaintyError
from instrument.uncertainty._figures import (
    Evaluator,
    Kind,
    direction_evaluator,
    distance_evaluator,
    drift_evaluator,
    kind_of,
    point_evaluator,
    unit_of,
)
from instrument.uncertainty._rotation import as_transform, decompose
from instrument.uncertainty._sampling import PoseSet, perturbed_tools
from instrument.uncertainty._summary import contribution, summarise

RULE_FRACTION = 0.25
METHOD = "GUM (JCGM 100) budget, Monte Carlo propagation (JCGM 101/102) through instrument.iso9283"


@dataclass(frozen=True)
class IsoRun:
    """What the uncertainty evaluation needs from an ISO 9283 run (SI: m, rad).

    Attributes
    ----------
    measured : mapping point → (n, 6) measured tool poses [x, y, z, a, b, c] in M, compensated
    commanded : mapping point → (6,) commanded tool pose in M
    tool_in_opr : (6,) pose or 4×4 matrix of the tool frame in the OPR frame, optional; with it the
        errors act on the OPR pose and reach the tool point through its lever arm
    truth : mapping point → (n, 6) true tool poses (simulation), optional: fills ``true``
    directions : mapping point → sequence of (n_h, 6) measured tool poses, one per approach
        direction, optional (vAP)
    directions_truth : the same for the true poses, optional
    """

    measured: Mapping[str, Any]
    commanded: Mapping[str, Any]
    tool_in_opr: Any = None
    truth: Mapping[str, Any] | None = None
    directions: Mapping[str, Sequence[Any]] | None = None
    directions_truth: Mapping[str, Sequence[Any]] | None = None


@dataclass(frozen=True)
class FigureUncertainty:
    """One figure's value with its measurement uncertainty (SI: ``unit`` m or rad).

    ``value`` is the best estimate (the ISO formula's ``uncorrected_value`` minus the estimated
    noise bias, unless the bias was carried in U); ``confidence_interval`` is the sampling interval
    ``instrument.iso9283`` computes (None where it computes none); ``mc_interval`` the Monte Carlo
    coverage interval at the probability that k gives for a normal distribution (95.45 % for k = 2).
    """

    name: str
    unit: str
    value: float
    expanded_uncertainty: float
    coverage_factor: float
    standard_uncertainty: float
    uncorrected_value: float
    noise_bias: float
    bias_corrected: bool
    contributions: Mapping[str, float]
    confidence_interval: tuple[float, float] | None
    mc_interval: tuple[float, float]
    characteristic: float
    true: float | None = None

    @property
    def ratio(self) -> float:
        """U / characteristic (inf for a zero characteristic)."""
        return self.expanded_uncertainty / self.characteristic if self.characteristic > 0 else math.inf

    @property
    def meets_25_percent_rule(self) -> bool:
        return self.ratio <= RULE_FRACTION

    @property
    def error(self) -> float | None:
        """value − true (simulation only)."""
        return None if self.true is None else self.value - self.true

    def to_dict(self) -> dict[str, Any]:
        """The export shape: value, expanded_uncertainty, coverage_factor, confidence_interval, true,
        and the figure's budget."""
        return {
            "value": self.value,
            "expanded_uncertainty": self.expanded_uncertainty,
            "coverage_factor": _plain_number(self.coverage_factor),
            "confidence_interval": None if self.confidence_interval is None else list(self.confidence_interval),
            "true": self.true,
            "unit": self.unit,
            "budget": {
                "standard_uncertainty": self.standard_uncertainty,
                "uncorrected_value": self.uncorrected_value,
                "noise_bias": self.noise_bias,
                "bias_corrected": self.bias_corrected,
                "contributions": dict(self.contributions),
                "mc_interval": list(self.mc_interval),
                "characteristic": self.characteristic,
                "ratio_to_characteristic": None if math.isinf(self.ratio) else self.ratio,
                "meets_25_percent_rule": self.meets_25_percent_rule,
            },
        }


FigureTable = Mapping[str, Mapping[str, FigureUncertainty]]


@dataclass(frozen=True)
class IsoUncertainty:
    """Every figure of a run with its uncertainty, grouped as the export shows them.

    ``points``: point → figure → FigureUncertainty (RP, AP and, when asked, drift);
    ``distances``: "P2-P4" → AD/RD figures; ``directions``: point → vAP figures.
    ``outside_validity``: point → components whose value lies beyond a point term's validity range.
    """

    points: FigureTable
    distances: FigureTable
    directions: FigureTable
    budget: UncertaintyBudget
    outside_validity: Mapping[str, tuple[str, ...]]
    draws: int
    seed: int
    coverage_factor: float
    bias_corrected: bool
    notes: tuple[str, ...] = field(default_factory=tuple)

    def figures(self) -> Iterator[tuple[str, str, FigureUncertainty]]:
        """(group, owner, figure) for every figure."""
        for group, table in (("points", self.points), ("distances", self.distances), ("directions", self.directions)):
            for owner, figures in table.items():
                for figure in figures.values():
                    yield group, owner, figure

    def above_25_percent(self) -> list[tuple[str, str, str]]:
        """(group, owner, figure name) of every figure that fails the 25 % rule."""
        return [(g, o, f.name) for g, o, f in self.figures() if not f.meets_25_percent_rule]

    def to_dict(self) -> dict[str, Any]:
        def table(t: FigureTable) -> dict[str, Any]:
            return {owner: {name: f.to_dict() for name, f in figures.items()} for owner, figures in t.items()}

        return {
            "method": METHOD,
            "coverage_factor": _plain_number(self.coverage_factor),
            "bias_policy": "corrected" if self.bias_corrected else "carried in U",
            "draws": self.draws,
            "seed": self.seed,
            "budget": self.budget.to_dict(),
            "outside_validity": {p: list(c) for p, c in self.outside_validity.items()},
            "notes": list(self.notes),
            "points": table(self.points),
            "distances": table(self.distances),
            "directions": table(self.directions),
        }


def iso_uncertainty(
    run: IsoRun,
    budget: UncertaintyBudget,
    *,
    draws: int = 1000,
    seed: int = 0,
    coverage_factor: float = 2.0,
    confidence: float = 0.95,
    distance_pairs: Sequence[tuple[str, str]] = (),
    drift_cycles: int | None = None,
    characteristics: Mapping[str, float] | None = None,
    correct_bias: bool = True,
    contributions: bool = True,
    contribution_draws: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> IsoUncertainty:
    """Measurement uncertainty of every ISO 9283 figure of a run, by Monte Carlo.

    Parameters
    ----------
    run : IsoRun
    budget : UncertaintyBudget
    draws : int, Monte Carlo draws (≥ 50; the relative standard error of u is ≈ 1/√(2·draws))
    seed : int, the generator's seed (same inputs and seed → same result)
    coverage_factor : float, k (2)
    confidence : float, level of the sampling intervals taken from ``instrument.iso9283``
    distance_pairs : pairs of points for AD/RD (e.g. [("P2", "P4")]); their poses pair cycle by cycle
    drift_cycles : int, optional; drift = first ``drift_cycles`` cycles against the last ones
    characteristics : mapping figure name → the characteristic for the 25 % rule (e.g. a robot's
        specified RP_l); default the figure's own magnitude
    correct_bias : bool, correct the noise bias (default) or carry it in U
    contributions : bool, also evaluate each term's contribution (one extra Monte Carlo per term)
    contribution_draws : int, draws of each of those (default max(200, draws // 4))
    progress : callable(k, n), optional; called after each of the n Monte Carlo passes (the budget's, then
        one per term for the contributions), so that a caller can say how far the evaluation is

    Returns
    -------
    IsoUncertainty

    Raises
    ------
    UncertaintyError
        For unusable input (one line naming the argument).
    """
    from scipy import special
    draws = _count(draws, "draws", 50)
    if not coverage_factor > 0:
        raise UncertaintyError(f"coverage_factor: expected > 0, got {coverage_factor}")
    if not isinstance(budget, UncertaintyBudget):
        raise UncertaintyError(f"budget: expected an UncertaintyBudget, got {type(budget).__name__}")
    transform = _transform(run.tool_in_opr)
    sets = _pose_sets(run.measured, transform, "measured")
    commanded = _commanded(run.commanded, sets)
    notes: list[str] = []
    evaluators = _evaluators(sets, commanded, distance_pairs, drift_cycles, notes)
    direction_sets = _direction_sets(run.directions, transform, sets, "directions")
    if direction_sets:
        sets = sets + [s for group in direction_sets.values() for s in group]
        evaluators += [direction_evaluator(point, tuple(s.label for s in group))
                       for point, group in direction_sets.items()]
    measured = {s.label: s.tool for s in sets}
    baseline = _evaluate_all(evaluators, measured)
    rng = np.random.default_rng(seed)
    passes = 1 + (sum(1 for term in budget.terms if term.active) if contributions else 0)
    samples = _monte_carlo(evaluators, sets, budget, transform, draws, rng)
    done = 1
    if progress is not None:
        progress(done, passes)
    per_term: dict[str, dict[tuple[str, str, str], np.ndarray]] = {}
    if contributions:
        extra = _count(contribution_draws, "contribution_draws", 50) if contribution_draws else max(200, draws // 4)
        for index, term in enumerate(budget.terms):
            if not term.active:
                per_term[term.name] = {key: np.full(extra, value) for key, value in baseline.items()}
                continue
            per_term[term.name] = _monte_carlo(evaluators, sets, budget.only(term.name), transform, extra,
                                               np.random.default_rng([seed, index + 1]))
            done += 1
            if progress is not None:
                progress(done, passes)
    truth = _truth_values(run, transform, evaluators, sets)
    intervals = _intervals(evaluators, measured, confidence)
    characteristics = dict(characteristics or {})
    probability = float(special.erf(coverage_factor / math.sqrt(2.0)))
    tables: dict[str, dict[str, dict[str, FigureUncertainty]]] = {"points": {}, "distances": {}, "directions": {}}
    for key, value in baseline.items():
        group, owner, name = key
        figure = _summarise(name, value, samples[key], coverage_factor, probability, correct_bias,
                            {t: per_term[t][key] for t in per_term}, intervals.get(key),
                            characteristics.get(name), truth.get(key))
        tables[group].setdefault(owner, {})[name] = figure
    return IsoUncertainty(
        points=tables["points"], distances=tables["distances"], directions=tables["directions"], budget=budget,
        outside_validity=_outside_validity(budget, sets), draws=draws, seed=int(seed),
        coverage_factor=float(coverage_factor), bias_corrected=bool(correct_bias), notes=tuple(notes))


# -- the pieces -----------------------------------------------------------------------------------


def _summarise(name, value, samples, k, probability, correct_bias, term_samples, interval, characteristic, true):
    kind = kind_of(name)
    squared = kind is Kind.NON_NEGATIVE
    summary = summarise(value, samples, k, probability, squared=squared)
    contributions = {t: contribution(summary.estimate, s, k, squared=squared) for t, s in term_samples.items()}
    estimate = summary.estimate if correct_bias else value
    bias = summary.bias
    expanded = summary.expanded_uncertainty if correct_bias else summary.expanded_uncertainty + abs(bias)
    low, high = summary.interval
    if kind is Kind.ABSOLUTE:  # propagated signed, reported as a magnitude
        bias = abs(value) - abs(summary.estimate)
        value, estimate = abs(value), abs(estimate)
        low, high = (0.0, max(-low, high)) if low < 0 < high else (min(abs(low), abs(high)), max(abs(low), abs(high)))
        true = None if true is None else abs(true)
    magnitude = abs(estimate) if characteristic is None else float(characteristic)
    return FigureUncertainty(
        name=name, unit=unit_of(name), value=float(estimate), expanded_uncertainty=float(expanded),
        coverage_factor=float(k), standard_uncertainty=summary.standard_uncertainty,
        uncorrected_value=float(value), noise_bias=float(bias),
        bias_corrected=bool(correct_bias), contributions=contributions, confidence_interval=interval,
        mc_interval=(float(low), float(high)), characteristic=magnitude, true=None if true is None else float(true))


def _monte_carlo(evaluators, sets, budget, transform, draws, rng) -> dict[tuple[str, str, str], np.ndarray]:
    tools = perturbed_tools(sets, budget, transform, draws, rng)
    keys = [(e.group, e.owner, name) for e in evaluators for name in e.names]
    out = np.empty((len(keys), draws))
    for i in range(draws):
        values = _evaluate_all(evaluators, {label: array[i] for label, array in tools.items()})
        out[:, i] = [values[key] for key in keys]
    return dict(zip(keys, out))


def _evaluate_all(evaluators: Sequence[Evaluator], poses) -> dict[tuple[str, str, str], float]:
    out: dict[tuple[str, str, str], float] = {}
    for e in evaluators:
        try:
            values = e.compute(poses)
        except ISO9283Error as exc:
            raise UncertaintyError(f"{e.group} {e.owner}: {exc}") from None
        out.update({(e.group, e.owner, name): values[name] for name in e.names})
    return out


def _intervals(evaluators, poses, confidence) -> dict[tuple[str, str, str], tuple[float, float]]:
    out = {}
    for e in evaluators:
        if e.intervals is not None:
            out.update({(e.group, e.owner, name): ci for name, ci in e.intervals(poses, confidence).items()})
    return out


def _truth_values(run: IsoRun, transform, evaluators, sets) -> dict[tuple[str, str, str], float]:
    if run.truth is None:
        return {}
    true_sets = _pose_sets(run.truth, transform, "truth")
    measured_n = {s.label: len(s.tool) for s in sets}
    poses = {s.label: s.tool for s in true_sets}
    if run.directions_truth is not None:
        for group in _direction_sets(run.directions_truth, transform, true_sets, "directions_truth").values():
            poses.update({s.label: s.tool for s in group})
    for label, n in measured_n.items():
        if label not in poses:
            raise UncertaintyError(f"truth: no true poses for {label!r}")
        if len(poses[label]) != n:
            raise UncertaintyError(f"truth[{label!r}]: {len(poses[label])} poses for {n} measured ones")
    return _evaluate_all(evaluators, poses)


def _evaluators(sets, commanded, distance_pairs, drift_cycles, notes) -> list[Evaluator]:
    by_label = {s.label: s for s in sets}
    evaluators = [point_evaluator(s.label, commanded[s.label]) for s in sets]
    if drift_cycles is not None:
        cycles = _count(drift_cycles, "drift_cycles", 2)
        for s in sets:
            if 2 * cycles <= len(s.tool):
                evaluators.append(drift_evaluator(s.label, commanded[s.label], cycles))
            else:
                notes.append(f"{s.label}: no drift figures ({len(s.tool)} poses; {cycles} first + {cycles} last "
                             "needed)")
    for pair in distance_pairs:
        try:
            first, second = pair
        except (TypeError, ValueError):
            raise UncertaintyError(f"distance_pairs: expected (point, point) pairs, got {pair!r}") from None
        missing = [p for p in (first, second) if p not in by_label]
        if missing:
            raise UncertaintyError(f"distance_pairs: unknown point(s) {', '.join(map(str, missing))}")
        if len(by_label[first].tool) != len(by_label[second].tool):
            notes.append(f"{first}-{second}: no AD/RD ({len(by_label[first].tool)} and {len(by_label[second].tool)} "
                         "poses do not pair cycle by cycle)")
            continue
        evaluators.append(distance_evaluator(first, second, commanded[first], commanded[second]))
    return evaluators


def _pose_sets(poses: Mapping[str, Any], transform, name: str) -> list[PoseSet]:
    if not isinstance(poses, Mapping) or not poses:
        raise UncertaintyError(f"{name}: expected a mapping point → (n, 6) poses with at least one point")
    return [_pose_set(str(point), str(point), array, transform, f"{name}[{point!r}]") for point, array in poses.items()]


def _pose_set(label: str, point: str, poses, transform, name: str) -> PoseSet:
    try:
        tool = np.array(poses, dtype=float)
    except (TypeError, ValueError):
        raise UncertaintyError(f"{name}: expected an (n, 6) array of numbers") from None
    if tool.ndim != 2 or tool.shape[1] != 6 or len(tool) < 2:
        raise UncertaintyError(f"{name}: expected (n ≥ 2, 6) poses [x, y, z, a, b, c], got shape {tool.shape}")
    if not np.all(np.isfinite(tool)):
        raise UncertaintyError(f"{name}: non-finite pose value")
    opr = tool if transform is None else decompose(tool, *transform)
    return PoseSet(label, point, tool, opr)


def _direction_sets(directions, transform, sets, name) -> dict[str, list[PoseSet]]:
    if directions is None:
        return {}
    points = {s.point for s in sets}
    out: dict[str, list[PoseSet]] = {}
    for point, group in directions.items():
        if point not in points:
            raise UncertaintyError(f"{name}: unknown point {point!r}")
        if isinstance(group, np.ndarray) or len(group) < 2:
            raise UncertaintyError(f"{name}[{point!r}]: expected ≥ 2 pose sets, one per approach direction")
        out[str(point)] = [_pose_set(f"{point}@{h + 1}", str(point), poses, transform, f"{name}[{point!r}][{h}]")
                           for h, poses in enumerate(group)]
    return out


def _commanded(commanded: Mapping[str, Any], sets: Sequence[PoseSet]) -> dict[str, np.ndarray]:
    out = {}
    for s in sets:
        if s.label not in commanded:
            raise UncertaintyError(f"commanded: no commanded pose for point {s.label!r}")
        array = np.asarray(commanded[s.label], dtype=float).reshape(-1)
        if array.shape != (6,) or not np.all(np.isfinite(array)):
            raise UncertaintyError(f"commanded[{s.label!r}]: expected a finite (6,) pose [x, y, z, a, b, c]")
        out[s.label] = array
    return out


def _transform(tool_in_opr) -> tuple[np.ndarray, np.ndarray] | None:
    if tool_in_opr is None:
        return None
    try:
        rotation, translation = as_transform(tool_in_opr)
    except ValueError as exc:
        raise UncertaintyError(f"tool_in_opr: {exc}") from None
    if not (np.all(np.isfinite(rotation)) and np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-9)):
        raise UncertaintyError("tool_in_opr: the rotation part is not a rotation matrix")
    return rotation, translation


def _outside_validity(budget: UncertaintyBudget, sets: Sequence[PoseSet]) -> dict[str, tuple[str, ...]]:
    out: dict[str, tuple[str, ...]] = {}
    for s in sets:
        beyond = set()
        for term in budget.terms:
            if term.correlation is Correlation.POINT and term.validity is not None:
                distance = term.beyond_validity(s.value)
                beyond |= {c for c, d, u in zip(COMPONENTS, distance, term.standard_uncertainty) if d > 0 and u > 0}
        if beyond:
            out[s.label] = tuple(c for c in COMPONENTS if c in beyond)
    return out


def _count(value, name: str, minimum: int) -> int:
    try:
        number = int(value)
    except (TypeError, ValueError):
        raise UncertaintyError(f"{name}: expected an integer ≥ {minimum}, got {value!r}") from None
    if number != value or number < minimum:
        raise UncertaintyError(f"{name}: expected an integer ≥ {minimum}, got {value!r}")
    return number


def _plain_number(value: float) -> float | int:
    return int(value) if float(value).is_integer() else float(value)
