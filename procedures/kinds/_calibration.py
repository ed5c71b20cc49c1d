"""What the two calibration kinds share: the point grid and the analysis into a calibration record."""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any

import numpy as np
from pydantic import ValidationInfo

from procedures._science import COMPONENTS
from procedures._store import Sample
from procedures.kinds._protocol import Analysis, AnalysisContext

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


def analyse_calibration(samples: Sequence[Sample], ctx: AnalysisContext, *, kind: str,
                        component_of_axis: Mapping[str, str], reference_instrument: str,
                        record_path: str | None) -> Analysis:
    """Fit a calibration record on the run's (measured, reference, group, point) rows and write it.

    Parameters
    ----------
    samples : the run's samples; failed ones and other phases are skipped
    ctx : the analysis context (science, run folder, truth of a simulated cell)
    kind : ``"displacement"`` or ``"angle"``: names the record file and the results
    component_of_axis : the pose component each axis calibrates (``{"x": "a"}`` for angles)
    reference_instrument : named in the record's provenance
    record_path : where to write the record; default ``<run folder>/calibration-<kind>.json``
    """
    data: dict[str, list[dict[str, Any]]] = {}
    for sample in samples:
        if not sample.ok or sample.phase != "calibration" or sample.meta is None or sample.solved is None:
            continue
        component = component_of_axis[sample.meta["axis"]]
        index = COMPONENTS.index(component)
        reference = sample.reference or {}
        entry = {"group": sample.meta["group"], "repeat": sample.meta["repeat"], "point": sample.meta["point"],
                 "nominal": sample.meta["nominal"], "measured": sample.solved["pose"][index],
                 "reference": reference["value"], "datum_set_at": reference.get("datum_set_at")}
        if ctx.truth is not None and sample.t_measured is not None:
            state = ctx.truth.at(sample.t_measured)
            if state is not None:
                true_pose = list(state["opr_in_m"]["t"]) + list(state["opr_in_m"]["euler"])
                entry["true"] = true_pose[index]
        data.setdefault(component, []).append(entry)
    if not data:
        raise ValueError("no successful calibration samples to fit")
    for rows in data.values():
        split_datum_groups(rows)
    fit = ctx.science.fit_calibration(kind, data, {
        "run_id": ctx.run_id, "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "references": [{"instrument": reference_instrument, "components": sorted(data)}]})
    path = record_file(record_path, ctx, kind)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(fit.record_json, encoding="utf-8")
    results = {
        "kind": f"{kind}_calibration", "record_path": str(path.resolve()), "record_id": fit.record_id,
        "data": data, "curves": fit.curves, "summary": fit.summary,
        "failed_samples": sum(1 for s in samples if not s.ok),
    }
    return Analysis(results=results, calibration_record_id=fit.record_id)


def split_datum_groups(rows: list[dict[str, Any]]) -> None:
    """Make each reference datum of a group its own calibration group, in place.

    A group whose reference was re-established (``datum_set_at`` differs between its rows, see
    ``displacement_calibration``) holds rows with different, unknown offsets: exactly what the
    calibration's group alignment estimates per group. Then every (group, datum) becomes a group,
    numbered from the largest (the alignment's reference) down; ``plan_group`` and ``datum`` (0 for
    a group's first datum) keep where each row came from. Rows of groups with one datum each keep
    their numbers.
    """
    segments: dict[tuple[int, float], list[dict[str, Any]]] = {}
    for row in rows:
        stamp = row.pop("datum_set_at", None)
        segments.setdefault((row["group"], -1.0 if stamp is None else float(stamp)), []).append(row)
    if len(segments) == len({group for group, _ in segments}):
        return
    for group in {group for group, _ in segments}:
        for ordinal, key in enumerate(sorted(k for k in segments if k[0] == group)):
            for row in segments[key]:
                row["plan_group"], row["datum"] = group, ordinal
    for new_group, key in enumerate(sorted(segments, key=lambda k: (-len(segments[k]), k))):
        for row in segments[key]:
            row["group"] = new_group


def calibration_summary_lines(results: Mapping[str, Any]) -> list[str]:
    """``instrument show``: where the record went."""
    return [f"record     {results['record_path']} ({results['record_id']})"]
