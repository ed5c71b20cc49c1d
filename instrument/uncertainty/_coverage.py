"""Coverage of U against known truth: does |value − true| ≤ U hold as often as k = 2 promises?

Feed it runs whose truth is known — synthetic runs (``synthetic_iso_run``) or, later, runs on the
simulated cell (measured poses plus the twins' true poses per point, as ``IsoRun(truth=…)``) —
and it reports per figure, pooled over points and runs:

- coverage: the fraction of |value − true| ≤ U (target 93–98 % for k = 2);
- tightness: median U / RMS(value − true); about 2 for a well-sized Gaussian U (U = 2u, RMS = u),
  larger when U is conservative;
- the same two for the other bias policy (the ISO formula's value, the bias carried in U), so that
  the choice of correcting the bias is measured, not asserted.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from instrument._conventions import ARCSEC
from instrument.uncertainty._budget import UncertaintyBudget
from instrument.uncertainty._errors import UncertaintyError
from instrument.uncertainty._figures import unit_of
from instrument.uncertainty._propagate import IsoRun, IsoUncertainty, iso_uncertainty

TARGET = (0.93, 0.98)


@dataclass(frozen=True)
class CoverageCase:
    """One run with known truth (``run.truth`` set) and the budget its data give."""

    run: IsoRun
    budget: UncertaintyBudget
    distance_pairs: tuple[tuple[str, str], ...] = ()
    drift_cycles: int | None = None


@dataclass(frozen=True)
class CoverageRow:
    """One figure (e.g. ``rp_l``), pooled over its points and runs (SI errors and U)."""

    figure: str
    unit: str
    count: int
    coverage: float
    tightness: float
    mean_error: float
    rms_error: float
    median_expanded: float
    coverage_carried: float
    tightness_carried: float
    mean_error_carried: float
    median_expanded_carried: float

    @property
    def in_target(self) -> bool:
        return TARGET[0] <= self.coverage <= TARGET[1]


@dataclass(frozen=True)
class CoverageTable:
    rows: tuple[CoverageRow, ...]
    runs: int

    def row(self, figure: str) -> CoverageRow:
        for r in self.rows:
            if r.figure == figure:
                return r
        raise KeyError(figure)

    def outside_target(self) -> list[str]:
        """Figures whose coverage lies outside 93–98 %."""
        return [r.figure for r in self.rows if not r.in_target]

    def to_dict(self) -> dict:
        return {"runs": self.runs, "target": list(TARGET), "rows": [r.__dict__ | {"in_target": r.in_target}
                                                                    for r in self.rows]}

    def format(self) -> str:
        """A plain-text table in µm / arc-seconds."""
        header = (f"{'figure':<7} {'n':>5} {'coverage':>8} {'tight':>6} {'mean err':>9} {'RMS err':>8} "
                  f"{'med U':>8} | {'cov. carried':>12} {'tight':>6} {'mean err':>9}  unit")
        lines = [header, "-" * len(header)]
        for r in self.rows:
            scale, unit = (1e6, "µm") if r.unit == "m" else (1.0 / ARCSEC, "″")
            lines.append(
                f"{r.figure:<7} {r.count:>5} {r.coverage:>8.3f} {r.tightness:>6.2f} {r.mean_error * scale:>9.3f} "
                f"{r.rms_error * scale:>8.3f} {r.median_expanded * scale:>8.3f} | {r.coverage_carried:>12.3f} "
                f"{r.tightness_carried:>6.2f} {r.mean_error_carried * scale:>9.3f}  {unit}")
        return "\n".join(lines)


def coverage_study(cases: Iterable[CoverageCase], *, draws: int = 300, seed: int = 0) -> CoverageTable:
    """Evaluate every case's uncertainty (without per-term contributions) and tabulate coverage.

    Parameters
    ----------
    cases : runs with truth and their budgets
    draws : Monte Carlo draws per run
    seed : the i-th case uses seed + i
    """
    results = []
    for index, case in enumerate(cases):
        if case.run.truth is None:
            raise UncertaintyError(f"cases[{index}]: the run has no truth to compare with")
        results.append(iso_uncertainty(case.run, case.budget, draws=draws, seed=seed + index,
                                       distance_pairs=case.distance_pairs, drift_cycles=case.drift_cycles,
                                       contributions=False))
    return coverage_table(results)


def coverage_table(results: Sequence[IsoUncertainty]) -> CoverageTable:
    """Coverage and tightness per figure from evaluated runs whose figures carry ``true``."""
    pooled: dict[str, list[tuple[float, float, float, float]]] = {}
    for result in results:
        for _, _, f in result.figures():
            if f.true is None:
                continue
            carried_u = f.coverage_factor * f.standard_uncertainty + abs(f.noise_bias)
            pooled.setdefault(f.name, []).append((f.value - f.true, f.expanded_uncertainty,
                                                  f.uncorrected_value - f.true, carried_u))
    if not pooled:
        raise UncertaintyError("coverage: no figure carries a true value")
    rows = []
    for name, entries in pooled.items():
        error, expanded, error_carried, expanded_carried = (np.array(v) for v in zip(*entries))
        rms = float(np.sqrt(np.mean(error**2)))
        rms_carried = float(np.sqrt(np.mean(error_carried**2)))
        rows.append(CoverageRow(
            figure=name, unit=unit_of(name), count=len(entries),
            coverage=float(np.mean(np.abs(error) <= expanded)),
            tightness=float(np.median(expanded) / rms) if rms > 0 else math.inf,
            mean_error=float(error.mean()), rms_error=rms, median_expanded=float(np.median(expanded)),
            coverage_carried=float(np.mean(np.abs(error_carried) <= expanded_carried)),
            tightness_carried=float(np.median(expanded_carried) / rms_carried) if rms_carried > 0 else math.inf,
            mean_error_carried=float(error_carried.mean()),
            median_expanded_carried=float(np.median(expanded_carried))))
    return CoverageTable(tuple(rows), len(results))
