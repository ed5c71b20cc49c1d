"""What the two calibration kinds share: the point grid and the analysis into a calibration record."""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any

import numpy as np
from pydantic import ValidationInfo

from instrument import COMPONENTS, __version__
from instrument.environment import AirConditions
from procedures.kinds._conditions import local_time, operator_of
from procedures.kinds._environment import environment_summary
from procedures.kinds._parameters import MotionParameters
from procedures.kinds._protocol import RESULTS_VERSION, Analysis, AnalysisContext
from procedures.kinds._references import (
    HENE_WAVELENGTH_M,
    interferometer_reference,
    scale_uncertainty,
    table_reference,
)
from procedures.kinds.calibration._results import (
    add_datum_removed_curves,
    before_after,
    evaluation_view,
    off_axis_slopes,
    reference_vs_truth,
    residual_uncertainties,
)
from procedures.station import RunError
from procedures.store import Sample

MAX_PLAN_STEPS = 100_000
"""Largest plan a procedure file may ask for (a 30-cycle ISO run is 155 steps, the paper's
displacement calibration 405); more is a typo such as ``step_mm: 1e-9``, refused before any plan."""
MIN_POINTS_PER_LINE = 5  # instrument.compensation.calibrate leaves one point out over at least 5 points
MIN_REPEATS = 2  # ... and estimates its noise floor from repeated observations at a point


def line_points(start: float, stop: float, step: float) -> int:
    """How many points ``inclusive_range(start, stop, step)`` has (``MAX_PLAN_STEPS + 1`` if more)."""
    ratio = (stop - start) / step
    if not math.isfinite(ratio) or ratio > MAX_PLAN_STEPS:
        return MAX_PLAN_STEPS + 1
    return int(math.floor(ratio + 1e-9)) + 1


def inclusive_range(start: float, stop: float, step: float) -> np.ndarray:
    """``start, start + step, ...`` up to and including ``stop`` (within rounding)."""
    return start + step * np.arange(line_points(start, stop, step))


def stored_run(info: ValidationInfo) -> bool:
    """Whether the file being validated is a stored run's (``load_procedure(..., stored=True)``): it
    was accepted when it was queued, so rules added later for new runs do not refuse it now."""
    return isinstance(info.context, Mapping) and bool(info.context.get("stored"))


def check_calibration_size(points: int, lines: int, repeats: int, step_field: str, info: ValidationInfo) -> None:
    """Refuse a calibration plan that is too large, or (for a new run) one the fit cannot use.

    Raises ValueError naming the field first (so the error points at its line).
    """
    total = points * lines * repeats
    if points > MAX_PLAN_STEPS or total > MAX_PLAN_STEPS:
        shown = f"more than {MAX_PLAN_STEPS}" if points > MAX_PLAN_STEPS else str(points)
        raise ValueError(f"{step_field} gives {shown} points per line, a plan of "
                         f"{'more than ' + str(MAX_PLAN_STEPS) if points > MAX_PLAN_STEPS else total} steps; "
                         f"a procedure may have at most {MAX_PLAN_STEPS}")
    if stored_run(info):
        return
    if points < MIN_POINTS_PER_LINE:
        raise ValueError(f"{step_field} gives {points} points per line; the calibration fit needs at least "
                         f"{MIN_POINTS_PER_LINE} (a smaller step or a longer range)")
    if repeats < MIN_REPEATS:
        raise ValueError(f"repeats is {repeats}; the calibration fit needs at least {MIN_REPEATS} repeats "
                         "(its noise floor comes from repeated points)")


def check_record_path(value: str | None) -> str | None:
    """A record path must stay inside the runs folder: relative, without ``..``."""
    if value is None:
        return value
    parts = PurePosixPath(value).parts + PureWindowsPath(value).parts
    if not value.strip() or PurePosixPath(value).is_absolute() or PureWindowsPath(value).is_absolute() \
            or ".." in parts or "\x00" in value:
        raise ValueError(f"expected a path relative to the runs folder, without '..' (got {value!r}); "
                         "the record is written there (default: in the run's own folder)")
    return value


def record_file(record_path: str | None, ctx: AnalysisContext, kind: str) -> Path:
    """Where the record goes: ``record_path`` inside the runs folder, or ``<run folder>/calibration-<kind>.json``.

    Raises ValueError if the path leads out of the runs folder (a symbolic link, say).
    """
    if not record_path:
        return ctx.run_dir / f"calibration-{kind}.json"
    runs_dir = ctx.run_dir.parent.resolve()  # a run's folder is <runs folder>/<run id>
    check_record_path(record_path)
    path = (runs_dir / record_path).resolve()
    if not path.is_relative_to(runs_dir):
        raise ValueError(f"record_path {record_path!r} leads out of the runs folder {runs_dir} (to {path})")
    return path


def _lost_points(samples: Sequence[Sample]) -> str:
    """'; every sample failed at x point 3, z point 0 (...)': the calibration points without a single
    good sample (the usual reason a fit lacks points), or '' when there are none."""
    good: set[tuple[str, int]] = set()
    tried: dict[tuple[str, int], str] = {}
    for sample in samples:
        if sample.phase != "calibration" or not sample.meta or "axis" not in sample.meta:
            continue
        key = (str(sample.meta["axis"]), int(sample.meta.get("point", -1)))
        if sample.ok and sample.solved is not None:
            good.add(key)
        else:
            tried[key] = sample.error or "failed"
    lost = sorted(set(tried) - good)
    if not lost:
        return ""
    names = ", ".join(f"{axis} point {point}" for axis, point in lost[:6]) + (" ..." if len(lost) > 6 else "")
    return f"; every sample failed at {names} (the last: {tried[lost[-1]]})"


def analyse_calibration(samples: Sequence[Sample], ctx: AnalysisContext, *, kind: str,
                        component_of_axis: Mapping[str, str], reference_instrument: str,
                        record_path: str | None, params: MotionParameters, approach: str = "one",
                        wavelength_compensation: bool = False) -> Analysis:
    """Fit a calibration record on the run's (measured, reference, group, point, direction) rows, write
    it, and state the results honestly (docs/results.md, "Calibration run").

    Parameters
    ----------
    samples : the run's samples; failed ones and other phases are skipped
    ctx : the analysis context (science, run folder, truth of a simulated cell)
    kind : ``"displacement"`` or ``"angle"``: names the record file and the results
    component_of_axis : the pose component each axis calibrates (``{"x": "a"}`` for angles)
    reference_instrument : named in the record's provenance
    record_path : where to write the record; default ``<run folder>/calibration-<kind>.json``
    params : the run's parameters (frames per pose, operator)
    approach : the ``approach`` parameter ("one" or "both")
    wavelength_compensation : the displacement readings were compensated for the air
    """
    data: dict[str, list[dict[str, Any]]] = {}
    environment: list[Mapping[str, Any]] = []
    factors: list[float] = []
    lines: dict[str, list[tuple[Any, list[float]]]] = {}
    for sample in samples:
        if not sample.ok or sample.phase != "calibration" or not sample.meta or sample.solved is None:
            continue
        meta = sample.meta
        lines.setdefault(meta["axis"], []).append(((meta["group"], meta["repeat"], meta.get("approach")),
                                                   list(sample.solved.pose)))
        component = component_of_axis[sample.meta["axis"]]
        index = COMPONENTS.index(component)
        reference = sample.reference
        entry = {"group": sample.meta["group"], "repeat": sample.meta["repeat"], "point": sample.meta["point"],
                 "nominal": sample.meta["nominal"], "measured": sample.solved.pose[index],
                 "reference": reference.value, "datum_set_at": reference.readings.get("datum_set_at"),
                 "direction": sample.meta.get("approach")}
        if reference.environment:
            environment.append(reference.environment)
        compensation = reference.readings.get("wavelength_compensation")
        if compensation:
            factors.append(float(compensation["factor"]))
        if ctx.truth is not None and sample.t_measured is not None:
            state = ctx.truth.at(sample.t_measured)
            if state is not None:
                true_pose = list(state["opr_in_m"]["t"]) + list(state["opr_in_m"]["euler"])
                entry["true"] = true_pose[index]
        data.setdefault(component, []).append(entry)
    if not data:
        raise RunError("the calibration analysis has no successful sample to fit" + _lost_points(samples))
    for rows in data.values():
        join_datums(rows)
    air = environment_summary(environment)
    mean_air = None if air is None else air["mean"]
    if kind == "displacement":
        air_conditions = None
        if mean_air and all(mean_air.get(q) is not None for q in ("air_temperature_k", "pressure_pa",
                                                                    "relative_humidity")):
            air_conditions = AirConditions(mean_air["air_temperature_k"], mean_air["pressure_pa"],
                                           mean_air["relative_humidity"])
        scale = scale_uncertainty(air_conditions, HENE_WAVELENGTH_M, compensated=bool(factors))
        reference_entry = interferometer_reference(scale, compensated=bool(factors), air=mean_air,
                                                   frames_per_pose=params.frames_per_pose)
        reference_entry["off_axis"] = off_axis_slopes(lines)
        noise = dict.fromkeys(data, float(reference_entry["reading_noise_m"]))
        scales = dict.fromkeys(data, scale)
    else:
        reference_entry = table_reference(params.frames_per_pose)
        noise = dict.fromkeys(data, float(reference_entry["encoder_standard_uncertainty_rad"]))
        scales = dict.fromkeys(data, 0.0)
    reference_entry["instrument"] = reference_instrument
    reference_entry["components"] = sorted(data)
    temperature = None if mean_air is None or mean_air.get("air_temperature_k") is None \
        else mean_air["air_temperature_k"] - 273.15
    first = min((s.t_measured for s in samples if s.t_measured is not None), default=None)
    # Imported here: validating a procedure loads this module, and must not load the measurement core.
    from instrument.compensation import InsufficientCalibrationData

    try:
        fit = ctx.science.fit_calibration(kind, data, {
            "run_id": ctx.run_id, "date": local_time(first) or time.strftime("%Y-%m-%dT%H:%M:%S"),
            "references": [reference_entry], "temperature_c": temperature})
    except InsufficientCalibrationData as exc:  # degenerate data: one line saying why, never a crash
        raise RunError(f"the calibration analysis refused the data: {exc}{_lost_points(samples)}") from None
    path = record_file(record_path, ctx, kind)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(fit.record_json, encoding="utf-8")
    curves = fit.curves
    add_datum_removed_curves(curves)
    notes: list[str] = []
    deviations = []
    if kind == "displacement" and not factors:
        deviations.append({"code": "environment_not_recorded", "severity": "warning",
                           "message": "the interferometer's readings were not compensated for the air (no "
                                      "environmental reading): its scale is uncertain by "
                                      f"{scale * 1e6:.2g} ppm", "details": {"scale_standard_uncertainty": scale}})
    if approach == "one":
        deviations.append({"code": "one_directional", "severity": "warning",
                           "message": "every point was approached from below only: the record cannot correct the "
                                      "hysteresis of a run that approaches from above", "details": {}})
    results = {
        "kind": f"{kind}_calibration", "results_version": RESULTS_VERSION, "record_path": str(path.resolve()),
        "record_id": fit.record_id, "approach": approach, "data": data, "curves": curves, "summary": fit.summary,
        "evaluation": evaluation_view(fit.summary), "before_after": before_after(curves),
        "residual_uncertainty": residual_uncertainties(curves, data, reference_noise=noise, reference_scale=scales,
                                                       notes=notes),
        "reference_vs_truth": reference_vs_truth(data), "off_axis": reference_entry.get("off_axis"),
        "test_conditions": {
            "date": local_time(first), "operator": operator_of(params.operator), "software_version": __version__,
            "reference": reference_entry, "environment": air,
            "wavelength_compensation": None if not factors else {
                "applied": True, "equation": "modified Edlén (instrument.environment)", "factor_min": min(factors),
                "factor_max": max(factors), "factor_mean": float(np.mean(factors))},
        },
        "deviations": deviations, "notes": notes,
        "failed_samples": sum(1 for s in samples if not s.ok),
    }
    return Analysis(results=results, calibration_record_id=fit.record_id)


def join_datums(rows: list[dict[str, Any]]) -> None:
    """Bring every reference datum of a group onto the group's first one, in place.

    A group whose reference was re-established (``datum_set_at`` differs between its rows, see
    ``displacement_calibration``) holds rows whose references are offset by an unknown amount: the
    robot's repeatability where it was zeroed again (~10 µm). At one calibration point the
    instrument's systematic error is the same under both datums, so the offset is the mean, over
    the points measured under both, of the difference of (reference − measured) between them. The
    later datum's references are shifted by it (``datum_offset``; ``reference_raw`` keeps the
    value read; ``datum``: 0 for the first datum, 1 for the next ...), and the group keeps its
    repeats, as the calibration's noise floor needs. A datum that shares no point with the earlier
    ones (only possible with a single repeat) becomes a calibration group of its own instead, whose
    offset the group alignment estimates.
    """
    by_group: dict[int, dict[float, list[dict[str, Any]]]] = {}
    for row in rows:
        stamp = row.pop("datum_set_at", None)
        by_group.setdefault(row["group"], {}).setdefault(-1.0 if stamp is None else float(stamp), []).append(row)
    next_group = max(by_group, default=-1) + 1
    for segments in by_group.values():
        if len(segments) == 1:
            continue
        joined: list[dict[str, Any]] = []
        for ordinal, stamp in enumerate(sorted(segments)):  # in the order the datums were set
            segment = segments[stamp]
            offset = _datum_offset(joined, segment) if joined else 0.0
            for row in segment:
                row["datum"] = ordinal
                if offset is None:
                    row["group"] = next_group
                    continue
                row["reference_raw"], row["datum_offset"] = row["reference"], offset
                row["reference"] = row["reference"] - offset
            if offset is None:
                next_group += 1
            else:
                joined += segment


def _datum_offset(earlier: list[dict[str, Any]], later: list[dict[str, Any]]) -> float | None:
    """How much the ``later`` rows' references read above the ``earlier`` ones' (see ``join_datums``)."""
    def per_point(rows: list[dict[str, Any]]) -> dict[int, float]:
        values: dict[int, list[float]] = {}
        for row in rows:
            values.setdefault(row["point"], []).append(row["reference"] - row["measured"])
        return {point: float(np.mean(v)) for point, v in values.items()}

    before, after = per_point(earlier), per_point(later)
    common = sorted(set(before) & set(after))
    if not common:
        return None
    return float(np.mean([after[p] - before[p] for p in common]))
