"""Honest calibration results, as data for the report (docs/results.md, "Calibration run").

- Before/after per group with each group's datum removed: a group's reference is relative to its
  own zero (the interferometer's datum, the robot's place at the group's start), so its mean error is
  an offset of the group, not an error of the curve. "After" is given in-sample (the record applied
  to the data it was fitted on) and held-out (each interior point predicted by a fit without it).
- The evaluation rows of the record (every one held-out), with the method in force marked.
- The held-out residual's RMS per component with its uncertainty from the reference
  (``instrument.uncertainty.calibration_residual_uncertainty``).
- In simulation, the reference against the truth like with like: each group's datum offset
  (mean of reference − true) removed before the spread is shown.
All SI.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from instrument.uncertainty import UncertaintyError, calibration_residual_uncertainty

SCHEME_NOTE = ("Every row is held out. leave-one-point-out: each interior calibration point in turn is left out "
               "(all its repeats, groups and directions), the method refitted on the rest predicts it with its "
               "group's offset; leave-one-group-out: a whole group predicted by a fit on the others, its mean "
               "removed (a new start pose's offset cannot be known).")


def _stat(values: Sequence[float | None]) -> dict[str, Any] | None:
    known = np.array([v for v in values if v is not None], dtype=float)
    if known.size == 0:
        return None
    return {"rms": float(np.sqrt(np.mean(known**2))), "max_abs": float(np.max(np.abs(known))), "n": int(known.size)}


def _group_centred(values: Sequence[float], groups: Sequence[int]) -> list[float]:
    values_array, groups_array = np.asarray(values, dtype=float), np.asarray(groups)
    out = values_array.copy()
    for g in np.unique(groups_array):
        mask = groups_array == g
        out[mask] -= values_array[mask].mean()
    return out.tolist()


def add_datum_removed_curves(curves: dict[str, dict[str, Any]]) -> None:
    """Each curve gains ``error_before_datum_removed`` and ``error_after_datum_removed`` (in place)."""
    for curve in curves.values():
        groups = curve.get("group") or []
        for key in ("error_before", "error_after"):
            values = curve.get(key)
            curve[f"{key}_datum_removed"] = None if values is None else _group_centred(values, groups)
        curve.setdefault("error_after_held_out", None)
        curve.setdefault("direction", None)


def before_after(curves: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """Per component and group: RMS and max |error| before, after (in-sample) and after (held-out)."""
    out: dict[str, Any] = {}
    for component, curve in curves.items():
        groups = list(curve.get("group") or [])
        before = curve.get("error_before_datum_removed") or []
        after = curve.get("error_after_datum_removed") or []
        held = curve.get("error_after_held_out") or [None] * len(groups)
        per_group = {}
        for g in sorted(set(groups)):
            index = [i for i, label in enumerate(groups) if label == g]
            per_group[str(g)] = {"n": len(index), "before": _stat([before[i] for i in index]),
                                 "after_in_sample": _stat([after[i] for i in index]),
                                 "after_held_out": _stat([held[i] for i in index])}
        out[component] = {"datum_removed": True, "held_out_scheme": "leave-one-point-out", "groups": per_group,
                          "all": {"before": _stat(before), "after_in_sample": _stat(after),
                                  "after_held_out": _stat(held)}}
    return out


def evaluation_view(summary: Mapping[str, Any]) -> dict[str, Any] | None:
    """The record's evaluation rows (SI, all held out) with the method in force per component marked."""
    evaluation = summary.get("evaluation")
    if not isinstance(evaluation, Mapping):
        return None
    methods = dict(summary.get("methods") or {})
    rows = [{key: row.get(key) for key in ("component", "method", "scheme", "rms", "max_abs", "end_rms",
                                            "noise_floor", "n_heldout")}
            | {"in_force": methods.get(row.get("component")) == row.get("method")}
            for row in evaluation.get("rows", [])]
    return {"method_in_force": methods, "scheme_note": SCHEME_NOTE, "data": evaluation.get("data"), "rows": rows}


def residual_uncertainties(curves: Mapping[str, Mapping[str, Any]], data: Mapping[str, Sequence[Mapping[str, Any]]],
                           *, reference_noise: Mapping[str, float], reference_scale: Mapping[str, float],
                           notes: list[str]) -> dict[str, Any]:
    """``residual_rms_<c>`` per component: the held-out residual's RMS with its U (k = 2), and in
    simulation its true value (the residual against the truth in the group's datum)."""
    out: dict[str, Any] = {}
    for component, curve in curves.items():
        rows = data.get(component) or []
        held = curve.get("error_after_held_out")
        if not held or len(held) != len(rows):
            notes.append(f"{component}: no held-out residuals, no residual uncertainty")
            continue
        keep = [i for i, r in enumerate(held) if r is not None]
        residuals = np.array([held[i] for i in keep])
        reference = np.array([rows[i]["reference"] for i in keep])
        points = np.array([rows[i]["point"] for i in keep])
        true = None
        offsets = _datum_offsets(rows)
        if offsets is not None:
            true = np.array([held[i] + rows[i]["reference"] - rows[i]["true"] - offsets[rows[i]["group"]]
                             for i in keep])
        try:
            figure = calibration_residual_uncertainty(
                residuals, reference, points, component=component, reference_noise=reference_noise.get(component, 0.0),
                reference_scale=reference_scale.get(component, 0.0), scale_distribution="normal",
                true_residuals=true)
        except UncertaintyError as exc:
            notes.append(f"{component}: residual uncertainty not evaluated: {exc}")
            continue
        out[component] = figure.to_dict()
    return out


def _datum_offsets(rows: Sequence[Mapping[str, Any]]) -> dict[int, float] | None:
    """Mean (reference − true) per group, when every row carries the truth."""
    if not rows or not all("true" in r for r in rows):
        return None
    by_group: dict[int, list[float]] = {}
    for r in rows:
        by_group.setdefault(r["group"], []).append(r["reference"] - r["true"])
    return {g: float(np.mean(v)) for g, v in by_group.items()}


def reference_vs_truth(data: Mapping[str, Sequence[Mapping[str, Any]]]) -> dict[str, Any] | None:
    """Reference − true per component and group with the group's datum offset removed (simulation)."""
    out: dict[str, Any] = {}
    for component, rows in data.items():
        offsets = _datum_offsets(rows)
        if offsets is None:
            continue
        residual_by_group: dict[int, list[float]] = {}
        for r in rows:
            residual_by_group.setdefault(r["group"], []).append(r["reference"] - r["true"] - offsets[r["group"]])
        groups = {str(g): {"datum_offset": offsets[g], **(_stat(v) or {})}
                  for g, v in sorted(residual_by_group.items())}
        out[component] = {"groups": groups, "all": _stat([v for vs in residual_by_group.values() for v in vs])}
    return out or None


def off_axis_slopes(lines: Mapping[str, Sequence[tuple[Any, Sequence[float]]]]) -> dict[str, Any] | None:
    """How much the other components read change along each calibration line (the cross-axis error).

    Along a line the robot moves along one axis k of M; the other components of the OPR's true pose
    stay put (to within the robot's straightness and angular deviation), so the slope of each other
    component's measured value against the measured k is the instrument's cross-axis error, which a
    per-component compensation (a curve of each component's own value) cannot correct. It includes the
    robot's own deviation along the line: an upper estimate.

    Parameters
    ----------
    lines : axis k → [(line key, (6,) solved pose), ...] of every sample along that axis

    Returns
    -------
    ``{"slopes": {k: {j: s}}, "spread": {k: {j: std over lines}}, "lines": {k: count}}``: s in m/m for
    x, y, z and rad/m for a, b, c; None without two points on a line.
    """
    components = ("x", "y", "z", "a", "b", "c")
    slopes: dict[str, dict[str, float]] = {}
    spread: dict[str, dict[str, float]] = {}
    counts: dict[str, int] = {}
    for axis, samples in lines.items():
        k = components.index(axis)
        by_line: dict[Any, list[Sequence[float]]] = {}
        for key, pose in samples:
            by_line.setdefault(key, []).append(pose)
        fits = []
        for poses in by_line.values():
            array = np.asarray(poses, dtype=float)
            if len(array) < 2 or np.ptp(array[:, k]) <= 0:
                continue
            fits.append([np.polyfit(array[:, k], array[:, j], 1)[0] if j != k else 0.0 for j in range(6)])
        if not fits:
            continue
        fitted = np.asarray(fits)
        slopes[axis] = {c: float(v) for c, v in zip(components, fitted.mean(axis=0)) if c != axis}
        spread[axis] = {c: float(v) for c, v in zip(components, fitted.std(axis=0)) if c != axis}
        counts[axis] = len(fits)
    return {"slopes": slopes, "spread": spread, "lines": counts} if slopes else None
