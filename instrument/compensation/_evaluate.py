"""Honest evaluation: every score comes from observations the model was not fitted on.

Schemes
-------
- ``leave-one-point-out``: each interior calibration point in turn is left out — all its
  repeats, in every group and from both directions — the compensator is refitted on the rest
  (group alignment, hyper-parameter search and all) and predicts the left-out observations,
  each with its group's offset from that fit and its own approach direction. The two end points
  always stay in training: outside the calibrated range a record flags values instead of
  claiming a correction. Leaving a point out doubles the local step, so these figures are
  somewhat pessimistic for use between calibration points, and much less so than leaving out
  every k-th point.
- ``leave-one-group-out``: fit on the other groups, predict the whole held-out group (end points
  included). A new group's offset is unknown to the model (it comes from its start pose), so the
  group's mean residual is removed before scoring: this scores the shape of the error curve, as a
  new session from an unseen start pose sees it.

Every score is in SI units (m or rad) and is compared with the noise floor: the pooled repeat
scatter of the error (one observation's noise, instrument plus reference), which no curve can
remove. "End" figures are the held-out observations in the first and last calibration interval.
``EvaluationTable.data`` says which data each component was scored on (counts, directions, range
and a SHA-256 of the arrays).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields

import numpy as np

from instrument.compensation._compensators import Compensator
from instrument.compensation._data import (
    CalibrationData,
    InsufficientCalibrationData,
    as_data_mapping,
    data_noise_floor,
    display_unit,
)

LOPO = "leave-one-point-out"
LOGO = "leave-one-group-out"
SCHEMES = (LOPO, LOGO)
MIN_EVALUATION_POINTS = 5  # leaving one out must leave the 4 points a fit needs


@dataclass(frozen=True)
class EvaluationRow:
    """Held-out error of one method on one component under one scheme (SI units)."""

    component: str
    method: str
    scheme: str
    rms: float
    max_abs: float
    end_rms: float
    noise_floor: float
    n_heldout: int

    @property
    def ratio_to_floor(self) -> float:
        return self.rms / self.noise_floor if self.noise_floor > 0 else float("inf")

    def display(self) -> dict:
        """The row in display units: µm for x, y, z and arc-seconds for a, b, c."""
        unit, factor = display_unit(self.component)
        return {"component": self.component, "method": self.method, "scheme": self.scheme, "unit": unit,
                "rms": self.rms * factor, "max_abs": self.max_abs * factor, "end_rms": self.end_rms * factor,
                "noise_floor": self.noise_floor * factor, "ratio_to_floor": self.ratio_to_floor,
                "n_heldout": self.n_heldout}

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(frozen=True)
class EvaluationTable:
    """Held-out errors per component, method and scheme, and the data they were computed on.

    Attributes
    ----------
    rows : tuple of EvaluationRow
    data : component → ``CalibrationData.summary()`` of the data scored
    note : free text (e.g. for an evaluation carried over from an older record format)
    """

    rows: tuple[EvaluationRow, ...]
    data: dict[str, dict] = field(default_factory=dict)
    note: str = ""

    def select(self, component: str | None = None, method: str | None = None, scheme: str | None = None
               ) -> list[EvaluationRow]:
        return [r for r in self.rows if (component is None or r.component == component)
                and (method is None or r.method == method) and (scheme is None or r.scheme == scheme)]

    def row(self, component: str, method: str, scheme: str = LOPO) -> EvaluationRow:
        found = self.select(component, method, scheme)
        if not found:
            raise KeyError(f"no evaluation row for {component}/{method}/{scheme}")
        return found[0]

    def best(self, component: str, scheme: str = LOPO) -> str:
        """Method with the lowest held-out RMS under ``scheme`` (the one ``calibrate`` keeps)."""
        rows = self.select(component, scheme=scheme)
        if not rows:
            raise KeyError(f"no {scheme} evaluation rows for component {component}")
        return min(rows, key=lambda r: r.rms).method

    def format(self) -> str:
        """Plain-text table; linear components in µm, angular ones in arc-seconds."""
        header = ("component", "method", "scheme", "unit", "RMS", "max", "end RMS", "floor", "RMS/floor", "n")
        lines = []
        for r in self.rows:
            d = r.display()
            lines.append((r.component, r.method, r.scheme, d["unit"], f"{d['rms']:.3f}", f"{d['max_abs']:.3f}",
                          f"{d['end_rms']:.3f}", f"{d['noise_floor']:.3f}", f"{r.ratio_to_floor:.2f}",
                          str(r.n_heldout)))
        widths = [max([len(h)] + [len(line[i]) for line in lines]) for i, h in enumerate(header)]

        def fmt(cells: Iterable[str]) -> str:
            return "  ".join(c.ljust(wd) if i < 4 else c.rjust(wd) for i, (c, wd) in enumerate(zip(cells, widths)))

        out = [fmt(header), fmt("-" * wd for wd in widths), *(fmt(line) for line in lines)]
        for component, summary in self.data.items():
            out.append(f"{component}: {summary['n_observations']} observations, {summary['n_points']} points, "
                       f"{summary['n_groups']} groups, directions {summary['directions'] or 'not recorded'}, "
                       f"data sha256 {summary['data_sha256'][:12]}")
        if self.note:
            out.append(self.note)
        return "\n".join(out)

    def to_dict(self) -> dict:
        return {"rows": [r.to_dict() for r in self.rows], "data": self.data, "note": self.note}

    @classmethod
    def from_dict(cls, d: dict) -> EvaluationTable:
        rows = []
        for r in d["rows"]:
            values = {k: (float("nan") if r[k] is None else float(r[k]))
                      for k in ("rms", "max_abs", "end_rms", "noise_floor")}
            rows.append(EvaluationRow(str(r["component"]), str(r["method"]), str(r["scheme"]), **values,
                                      n_heldout=int(r["n_heldout"])))
        return cls(tuple(rows), {str(k): dict(v) for k, v in d.get("data", {}).items()}, str(d.get("note", "")))


def _stats(residual: np.ndarray, is_end: np.ndarray) -> tuple[float, float, float]:
    rms = float(np.sqrt(np.mean(residual**2)))
    end = float(np.sqrt(np.mean(residual[is_end] ** 2))) if np.any(is_end) else float("nan")
    return rms, float(np.max(np.abs(residual))), end


def _direction(data: CalibrationData, mask: np.ndarray) -> np.ndarray | None:
    return None if data.direction is None else data.direction[mask]


def leave_one_point_out_residuals(compensator: Compensator, data: CalibrationData) -> tuple[np.ndarray, np.ndarray]:
    """Held-out residuals (one per observation of the interior points) and their end-interval flags."""
    ordered = data.point_order()
    end_points = {ordered[1], ordered[-2]}
    residuals, ends = [], []
    for held in ordered[1:-1]:
        test = data.point == held
        model = compensator.fit(data.subset(~test))
        offsets = np.array([model.group_offset(g) for g in data.group[test]])
        residuals.append(data.error[test] + offsets - model.predict(data.measured[test], _direction(data, test)))
        ends.append(np.full(int(test.sum()), held in end_points))
    return np.concatenate(residuals), np.concatenate(ends)


def leave_one_group_out_residuals(compensator: Compensator, data: CalibrationData
                                  ) -> tuple[np.ndarray, np.ndarray]:
    """Held-out residuals of each whole group (its mean removed) and their end-interval flags."""
    ordered = data.point_order()
    end_points = [ordered[0], ordered[1], ordered[-2], ordered[-1]]
    residuals, ends = [], []
    for g in np.unique(data.group):
        test = data.group == g
        model = compensator.fit(data.subset(~test))
        r = data.error[test] - model.predict(data.measured[test], _direction(data, test))
        residuals.append(r - r.mean())
        ends.append(np.isin(data.point[test], end_points))
    return np.concatenate(residuals), np.concatenate(ends)


def evaluate(compensators: Mapping[str, Compensator] | Iterable[Compensator],
             calibration_data: CalibrationData | Mapping[str, CalibrationData] | Iterable[CalibrationData], *,
             schemes: tuple[str, ...] = SCHEMES) -> EvaluationTable:
    """Held-out RMS and maximum error of every compensator on every component.

    Parameters
    ----------
    compensators : mapping name → Compensator, or Compensators (named by ``.name``)
    calibration_data : CalibrationData, a sequence of them, or a mapping component → CalibrationData
    schemes : any of ``SCHEMES``; leave-one-group-out is skipped for single-group data

    Returns
    -------
    EvaluationTable
    """
    named = dict(compensators) if isinstance(compensators, Mapping) else {c.name: c for c in compensators}
    unknown = set(schemes) - set(SCHEMES)
    if unknown:
        raise ValueError(f"unknown evaluation scheme(s) {sorted(unknown)}; expected {SCHEMES}")
    rows, summaries = [], {}
    for component, data in as_data_mapping(calibration_data).items():
        if LOPO in schemes and data.n_points < MIN_EVALUATION_POINTS:
            raise InsufficientCalibrationData(f"{component}: leave-one-point-out needs at least "
                                              f"{MIN_EVALUATION_POINTS} calibration points, got {data.n_points}")
        floor = data_noise_floor(data)
        summaries[component] = data.summary()
        for name, compensator in named.items():
            for scheme in schemes:
                if scheme == LOGO:
                    if np.unique(data.group).size < 2:
                        continue
                    residual, ends = leave_one_group_out_residuals(compensator, data)
                else:
                    residual, ends = leave_one_point_out_residuals(compensator, data)
                rms, max_abs, end_rms = _stats(residual, ends)
                rows.append(EvaluationRow(component, name, scheme, rms, max_abs, end_rms, floor, int(residual.size)))
    return EvaluationTable(tuple(rows), summaries)
