"""Honest evaluation: every score comes from observations the model was not fitted on.

Schemes
-------
- ``k-fold``: the interior calibration points are dealt into k folds (every k-th point, so each
  fold's points have fitted neighbours); a fold leaves out whole points — all repeats of all
  groups. The two end points always stay in training: outside the calibrated range a record
  flags values instead of claiming a correction. The held-out residual of an observation of
  group g is (error + offset_g) − prediction, with offset_g estimated from the training data.
- ``leave-one-group-out``: fit on the other groups, predict the whole held-out group (end points
  included). A new group's offset is unknown to the model (it comes from its start pose), so the
  group's mean residual is removed before scoring: this scores the shape of the error curve.

Every score is compared with the noise floor: the pooled repeat scatter of the error (one
observation's noise, instrument plus reference), which no curve can remove. "End" figures are
the held-out points in the first and last calibration interval, where natural spline end
conditions put most of the error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from instrument.compensation._data import as_data_mapping, display_unit, noise_floor

SCHEMES = ("k-fold", "leave-one-group-out")


@dataclass(frozen=True)
class EvaluationRow:
    component: str
    method: str
    scheme: str
    rms: float  # SI units
    max_abs: float
    end_rms: float
    noise_floor: float
    n_heldout: int

    @property
    def ratio_to_floor(self) -> float:
        return self.rms / self.noise_floor if self.noise_floor > 0 else float("inf")

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@dataclass(frozen=True)
class EvaluationTable:
    """Held-out errors per component, method and scheme."""

    rows: tuple

    def select(self, component=None, method=None, scheme=None) -> list:
        return [r for r in self.rows if (component is None or r.component == component)
                and (method is None or r.method == method) and (scheme is None or r.scheme == scheme)]

    def row(self, component: str, method: str, scheme: str = "k-fold") -> EvaluationRow:
        found = self.select(component, method, scheme)
        if not found:
            raise KeyError(f"no evaluation row for {component}/{method}/{scheme}")
        return found[0]

    def best(self, component: str, scheme: str = "k-fold") -> str:
        """Method with the lowest held-out RMS (the default compensator for that component)."""
        rows = self.select(component, scheme=scheme)
        if not rows:
            raise KeyError(f"no evaluation rows for component {component}")
        return min(rows, key=lambda r: r.rms).method

    def format(self) -> str:
        """Plain-text table; linear components in µm, angular ones in arc-seconds."""
        header = ("component", "method", "scheme", "unit", "RMS", "max", "end RMS", "floor", "RMS/floor", "n")
        lines = []
        for r in self.rows:
            unit, factor = display_unit(r.component)
            lines.append((r.component, r.method, r.scheme, unit, f"{r.rms * factor:.3f}", f"{r.max_abs * factor:.3f}",
                          f"{r.end_rms * factor:.3f}", f"{r.noise_floor * factor:.3f}", f"{r.ratio_to_floor:.2f}",
                          str(r.n_heldout)))
        widths = [max(len(h), *(len(l[i]) for l in lines)) if lines else len(h) for i, h in enumerate(header)]
        fmt = lambda cells: "  ".join(
            c.ljust(wd) if i < 4 else c.rjust(wd) for i, (c, wd) in enumerate(zip(cells, widths))
        )
        out = [fmt(header), fmt(["-" * wd for wd in widths])]
        out += [fmt(l) for l in lines]
        return "\n".join(out)

    def to_dict(self) -> dict:
        return {"rows": [r.to_dict() for r in self.rows]}

    @classmethod
    def from_dict(cls, d: dict) -> EvaluationTable:
        return cls(tuple(EvaluationRow(**{**r, "n_heldout": int(r["n_heldout"])}) for r in d["rows"]))


def _stats(residual, is_end):
    rms = float(np.sqrt(np.mean(residual**2)))
    end = float(np.sqrt(np.mean(residual[is_end] ** 2))) if np.any(is_end) else float("nan")
    return rms, float(np.max(np.abs(residual))), end


def _point_order(data):
    labels = np.unique(data.point)
    centers = np.array([data.measured[data.point == p].mean() for p in labels])
    return labels[np.argsort(centers)]


def kfold_residuals(compensator, data, k: int = 5):
    """Held-out residuals (one per observation of the interior points) and their end flags."""
    ordered = _point_order(data)
    interior = ordered[1:-1]
    end_points = {ordered[1], ordered[-2]}
    residuals, ends = np.empty(0), np.empty(0, bool)
    error = data.error
    for fold in range(min(k, interior.size)):
        held = interior[fold::k]
        test = np.isin(data.point, held)
        model = compensator.fit(data.measured[~test], error[~test], data.group[~test], data.point[~test])
        offsets = np.array([model.group_offset(g) for g in data.group[test]])
        r = error[test] + offsets - model.predict(data.measured[test])
        residuals = np.concatenate([residuals, r])
        ends = np.concatenate([ends, np.isin(data.point[test], list(end_points))])
    return residuals, ends


def logo_residuals(compensator, data):
    ordered = _point_order(data)
    end_points = [ordered[0], ordered[1], ordered[-2], ordered[-1]]
    residuals, ends = np.empty(0), np.empty(0, bool)
    for g in np.unique(data.group):
        test = data.group == g
        model = compensator.fit(data.measured[~test], data.error[~test], data.group[~test], data.point[~test])
        r = data.error[test] - model.predict(data.measured[test])
        residuals = np.concatenate([residuals, r - r.mean()])
        ends = np.concatenate([ends, np.isin(data.point[test], end_points)])
    return residuals, ends


def evaluate(compensators, calibration_data, *, k: int = 5, schemes=SCHEMES) -> EvaluationTable:
    """Held-out RMS and maximum error of every compensator on every component.

    Parameters
    ----------
    compensators : mapping name → Compensator, or a sequence of Compensators (named by ``.name``)
    calibration_data : CalibrationData, a sequence of them, or a mapping component → CalibrationData
    k : folds of the k-fold scheme
    schemes : any of "k-fold", "leave-one-group-out" (the latter needs ≥ 2 groups)
    """
    if not isinstance(compensators, dict):
        compensators = {c.name: c for c in compensators}
    unknown = set(schemes) - set(SCHEMES)
    if unknown:
        raise ValueError(f"unknown evaluation scheme(s) {sorted(unknown)}; expected {SCHEMES}")
    rows = []
    for component, data in as_data_mapping(calibration_data).items():
        floor = noise_floor(data.error, data.group, data.point)
        for name, compensator in compensators.items():
            for scheme in schemes:
                if scheme == "leave-one-group-out":
                    if np.unique(data.group).size < 2:
                        continue
                    residual, ends = logo_residuals(compensator, data)
                else:
                    residual, ends = kfold_residuals(compensator, data, k)
                rms, max_abs, end_rms = _stats(residual, ends)
                rows.append(EvaluationRow(component, name, scheme, rms, max_abs, end_rms, floor, int(residual.size)))
    return EvaluationTable(tuple(rows))
