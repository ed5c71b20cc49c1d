"""The analysis of an ISO 9283 run: figures with their measurement uncertainty, the test conditions,
the deviations from the standard (docs/results.md, "ISO 9283 run").

The transform pass fits the robot↔M transform on the measured OPR positions; each attained OPR pose
(compensated when asked) becomes the tool point's pose; RP and AP per point come from
``instrument.iso9283``; their uncertainty from ``instrument.uncertainty`` with the budget of
``_iso_budget``. In simulation, "true" is the same pipeline on the twins' true OPR poses, with the
transform fitted on the true positions of the transform pass (see docs/results.md, "What true means").
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from instrument import COMPONENTS, __version__
from instrument.uncertainty import CoverageCase, IsoRun, UncertaintyBudget, UncertaintyError, iso_uncertainty
from procedures.kinds._conditions import local_time
from procedures.kinds._environment import environment_summary
from procedures.kinds._protocol import RESULTS_VERSION, AnalysisContext
from procedures.kinds.iso._budget import BudgetUnavailable, iso_budget, squareness_terms
from procedures.kinds.iso._parameters import IsoParameters
from procedures.kinds.iso._test_conditions import deviations_of, test_conditions
from procedures.station import euler_to_matrix, matrix_to_euler, tcp_in_m, ur_to_matrix
from procedures.store import Sample

if TYPE_CHECKING:
    from procedures.station import Compensator

DISTANCE_PAIR = ("P2", "P4")  # ISO 9283 §7.? distance accuracy and repeatability: P2 → P4 (the cube's diagonal)
LINEAR_FIGURES = {"rp_l", "ap_p", "ap_x", "ap_y", "ap_z"}
POINT_FIGURES = ("rp_l", "rp_a", "rp_b", "rp_c", "ap_p", "ap_x", "ap_y", "ap_z", "ap_a", "ap_b", "ap_c")
SEED = 0  # the Monte Carlo's: the same data give the same U


def _measured(sample: Sample) -> np.ndarray:
    """The step's best pose (corrected when a record was applied, else as solved)."""
    return np.asarray(sample.measured_pose(), dtype=float)


def _commanded_tcp(sample: Sample) -> list[float]:
    return list(sample.robot_target())


def _true_opr(ctx: AnalysisContext, sample: Sample) -> np.ndarray | None:
    if ctx.truth is None or sample.t_measured is None:
        return None
    state = ctx.truth.at(sample.t_measured)
    if state is None or "opr_in_m" not in state:
        return None
    return np.array(list(state["opr_in_m"]["t"]) + list(state["opr_in_m"]["euler"]), dtype=float)


def _fit(ctx: AnalysisContext, source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, float]:
    rotation, translation, rms = ctx.science.fit_rigid_transform(source, target)
    fitted = np.eye(4)
    fitted[:3, :3], fitted[:3, 3] = rotation, translation
    return fitted, float(rms)


def _spread(points: np.ndarray, centre: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((points - centre) ** 2, axis=1))))


def _approach_of(samples: Sequence[Sample]) -> tuple[dict[str, int | None], bool]:
    """The direction each component of a point was approached from (None if it varied or did not move)."""
    seen: dict[str, set[int | None]] = {c: set() for c in COMPONENTS}
    for s in samples:
        approach = s.reference.approach if isinstance(s.reference.approach, Mapping) else {}
        for c in COMPONENTS:
            seen[c].add(approach.get(c))
    varied = any(len(v) > 1 for v in seen.values())
    return {c: next(iter(v)) if len(v) == 1 else None for c, v in seen.items()}, varied


def analyse_iso(samples: Sequence[Sample], ctx: AnalysisContext, params: IsoParameters) -> dict[str, Any]:
    """Every figure of the run with its uncertainty, the test conditions and the deviations."""
    reference = ctx.station.frames.reference_tcp_pose
    opr_to_tool = ur_to_matrix(ctx.station.frames.tool_in_opr)
    notes: list[str] = []

    transform_samples = [s for s in samples if s.phase == "transform" and s.ok]
    fitted, mirror = np.eye(4), np.eye(4)
    transform: dict[str, Any] = {"fitted": False}
    transform_geometry = None
    if len(transform_samples) >= 3:
        source = np.array([tcp_in_m(reference, _commanded_tcp(s))[:3, 3] for s in transform_samples])
        target = np.array([_measured(s)[:3] for s in transform_samples])
        fitted, rms = _fit(ctx, source, target)
        centre = target.mean(axis=0)
        transform = {"fitted": True, "rotation": fitted[:3, :3].tolist(), "translation": fitted[:3, 3].tolist(),
                     "residual_rms": rms, "points": len(transform_samples), "spread": _spread(target, centre)}
        transform_geometry = {"points": len(transform_samples), "spread": transform["spread"], "centre": centre}
        true_targets = [_true_opr(ctx, s) for s in transform_samples]
        if ctx.truth is not None and all(t is not None for t in true_targets):
            true_fit, _ = _fit(ctx, source, np.array([t[:3] for t in true_targets if t is not None]))
            mirror = fitted @ np.linalg.inv(true_fit)  # the true frame's fit carried onto the measured one

    order: list[str] = []
    for sample in samples:
        if sample.phase == "iso" and sample.label not in order and sample.label is not None:
            order.append(sample.label)
    points: dict[str, Any] = {}
    measured_tools: dict[str, np.ndarray] = {}
    true_tools: dict[str, np.ndarray] = {}
    commanded_tools: dict[str, np.ndarray] = {}
    opr_barycentres: dict[str, np.ndarray] = {}
    per_frame: list[list[list[float]]] = []
    for label in order:
        mine = [s for s in samples if s.phase == "iso" and s.label == label and s.ok]
        if len(mine) < 2:
            points[label] = {"n": len(mine), "error": "fewer than 2 measured poses"}
            continue
        opr = np.array([_measured(s) for s in mine])
        poses = np.array([matrix_to_euler(euler_to_matrix(p) @ opr_to_tool) for p in opr])
        commanded = matrix_to_euler(fitted @ tcp_in_m(reference, _commanded_tcp(mine[0])) @ opr_to_tool)
        approach, varied = _approach_of(mine)
        if varied:
            notes.append(f"{label}: approached from different directions in different cycles")
        entry: dict[str, Any] = {
            "n": len(mine), "stats": ctx.science.iso_statistics(poses, commanded), "poses": poses.tolist(),
            "commanded": commanded.tolist(), "commanded_in_base": list(_commanded_tcp(mine[0])),
            "cycles": [s.meta.get("cycle") for s in mine], "t_measured": [s.t_measured for s in mine],
            "approach": approach,
        }
        true_opr = [_true_opr(ctx, s) for s in mine]
        if ctx.truth is not None and all(t is not None for t in true_opr):
            true = np.array([matrix_to_euler(mirror @ euler_to_matrix(t) @ opr_to_tool) for t in true_opr
                             if t is not None])
            entry["true_stats"] = ctx.science.iso_statistics(true, commanded)
            entry["true_poses"] = true.tolist()
            true_tools[label] = true
        points[label] = entry
        measured_tools[label], commanded_tools[label] = poses, commanded
        opr_barycentres[label] = opr.mean(axis=0)
        per_frame += [[list(p) for p in s.solved.per_frame] for s in mine if s.solved and s.solved.per_frame]

    applied_infos = [_info(c) for c in ctx.compensators]
    infos = applied_infos or _station_record_infos(ctx, notes)
    applied = {c for info in applied_infos for c in info.get("components", [])}
    environment = environment_summary([s.reference.environment for s in samples if s.ok and s.reference.environment])
    run_air = None if environment is None else environment["mean"].get("air_temperature_k")

    uncertainty: dict[str, Any]
    figures: dict[str, Any]
    if params.uncertainty_draws == 0:
        uncertainty = {"evaluated": False, "reason": "uncertainty_draws is 0"}
        figures = _figures_without_uncertainty(points)
    elif not measured_tools:
        uncertainty = {"evaluated": False, "reason": "no point has 2 measured poses"}
        figures = _figures_without_uncertainty(points)
    else:
        lever = None
        if transform_geometry is not None:
            barycentres = np.array([t[:, :3].mean(axis=0) for t in measured_tools.values()])
            lever = _spread(barycentres, transform_geometry["centre"])
            transform["lever"] = lever
        try:
            budget, estimator, off_axis = iso_budget(
                infos, applied, frames_per_pose=params.frames_per_pose,
                per_frame=per_frame if params.frames_per_pose >= 2 else None,
                transform=None if transform_geometry is None else {**transform_geometry, "lever": lever},
                run_air_k=run_air, positions={label: bary[:3].tolist() for label, bary in opr_barycentres.items()},
                squareness=(params.frame_squareness_urad or 0.0) * 1e-6)
            uncertainty, figures = _evaluate(params, budget, estimator, measured_tools, commanded_tools, true_tools,
                                             ctx.station.frames.tool_in_opr, ctx.progress)
            uncertainty["off_axis"] = off_axis
            uncertainty["frame_squareness_rad"] = None if params.frame_squareness_urad is None \
                else params.frame_squareness_urad * 1e-6
            if off_axis is None:
                notes.append("the displacement record states no off-axis slopes: the angles' cross-axis error is "
                             "not in U")
            if params.frame_squareness_urad is None:
                notes.append("frame squareness not stated: the position frame's squareness and rotation against "
                             "the angle frame (not calibrated) are not in U; AP and AD can be off by more than U")
        except (BudgetUnavailable, UncertaintyError) as exc:
            uncertainty = {"evaluated": False, "reason": str(exc)}
            figures = _figures_without_uncertainty(points)

    sessions = [s.to_stored() for s in ctx.sessions]
    first = min((s.t_measured for s in samples if s.t_measured is not None), default=None)
    conditions = test_conditions(params, ctx.station, points, sessions, environment, infos, applied_infos,
                                 date=local_time(first), software_version=__version__)
    results: dict[str, Any] = {
        "kind": "iso9283", "results_version": RESULTS_VERSION, "order": order, "points": points,
        "transform": transform, "components": list(COMPONENTS),
        "compensation": [c.record_id for c in ctx.compensators],
        "failed_samples": sum(1 for s in samples if not s.ok),
        "figures": figures, "uncertainty": uncertainty | {"notes": uncertainty.get("notes", []) + notes},
        "test_conditions": conditions,
    }
    results["deviations"] = deviations_of(params, conditions, points, uncertainty, infos, applied_infos,
                                          opr_barycentres, transform["fitted"])
    return results


def _info(compensator: Compensator) -> dict[str, Any]:
    info = getattr(compensator, "info", None)
    return dict(info()) if callable(info) else {"id": compensator.record_id, "components": [], "evaluation": {}}


def _station_record_infos(ctx: AnalysisContext, notes: list[str]) -> list[dict[str, Any]]:
    """The station's records, loaded only for what they say of the instrument (not applied)."""
    record = ctx.station.calibration.record
    paths = [] if not record else [record] if isinstance(record, str) else list(record)
    infos = []
    for path in paths:
        try:
            infos.append({**_info(ctx.science.load_compensator(path)), "path": path})
        except (OSError, ValueError, KeyError, TypeError) as exc:
            notes.append(f"calibration record {path} not read for the uncertainty: {exc}")
    return infos


def _evaluate(params: IsoParameters, budget: Any, estimator: Mapping[str, Any], measured: Mapping[str, np.ndarray],
              commanded: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray],
              tool_in_opr: Sequence[float], progress: Callable[[str, int, int], None] | None = None
              ) -> tuple[dict[str, Any], dict[str, Any]]:
    n = min(len(p) for p in measured.values())
    pairs = [DISTANCE_PAIR] if all(p in measured for p in DISTANCE_PAIR) else []
    drift = params.drift_cycles if params.drift_cycles is not None else max(2, n // 3)
    drift_cycles = drift if 2 * drift <= n else None
    run = IsoRun(measured=dict(measured), commanded=dict(commanded), tool_in_opr=ur_to_matrix(tool_in_opr),
                 truth=dict(truth) if truth and set(truth) == set(measured) else None)
    result = iso_uncertainty(run, budget, draws=params.uncertainty_draws, seed=SEED, distance_pairs=pairs,
                             drift_cycles=drift_cycles,
                             progress=None if progress is None else lambda k, n: progress("uncertainty", k, n))
    exported = result.to_dict()
    uncertainty = {
        "evaluated": True, "reason": None, "method": exported["method"], "coverage_factor": exported["coverage_factor"],
        "bias_policy": exported["bias_policy"], "draws": exported["draws"], "seed": exported["seed"],
        "budget": exported["budget"], "noise_estimator": dict(estimator), "distance_pairs": [list(p) for p in pairs],
        "drift_cycles": drift_cycles, "outside_validity": exported["outside_validity"],
        "above_25_percent": [list(item) for item in result.above_25_percent()], "notes": exported["notes"],
    }
    figures = {"points": exported["points"], "distances": exported["distances"],
               "directions": exported["directions"]}
    return uncertainty, figures


def _figures_without_uncertainty(points: Mapping[str, Any]) -> dict[str, Any]:
    """The figure objects from the ISO formula's values alone (no U)."""
    table: dict[str, Any] = {}
    for label, entry in points.items():
        stats, true = entry.get("stats"), entry.get("true_stats") or {}
        if not stats:
            continue
        table[label] = {name: figure_without_uncertainty(name, stats, true) for name in POINT_FIGURES if name in stats}
    return {"points": table, "distances": {}, "directions": {}}


def figure_without_uncertainty(name: str, stats: Mapping[str, Any], true: Mapping[str, Any]) -> dict[str, Any]:
    """One figure object from ``stats`` (``name``, ``name_ci``) and the matching true stats, no U."""
    interval = stats.get(f"{name}_ci")
    return {"value": stats[name], "expanded_uncertainty": None, "coverage_factor": 2,
            "confidence_interval": None if interval is None else list(interval), "true": true.get(name),
            "unit": "m" if name in LINEAR_FIGURES else "rad", "budget": None}


def coverage_case(results: Mapping[str, Any], tool_in_opr: Sequence[float], *,
                  frame_squareness: float | None = None) -> CoverageCase | None:
    """An ISO run's results (with truth and an evaluated budget) as a ``CoverageCase``, to check U against
    the truth with ``instrument.uncertainty.coverage_study``; None when the run has no truth or no budget.
    ``frame_squareness`` (rad): the budget with the squareness terms of that value instead of the run's."""
    uncertainty = results.get("uncertainty") or {}
    points = {label: entry for label, entry in (results.get("points") or {}).items() if "true_poses" in entry}
    if not uncertainty.get("evaluated") or not points or len(points) != len(results.get("points") or {}):
        return None
    run = IsoRun(measured={p: e["poses"] for p, e in points.items()},
                 commanded={p: e["commanded"] for p, e in points.items()},
                 tool_in_opr=ur_to_matrix(tool_in_opr), truth={p: e["true_poses"] for p, e in points.items()})
    pairs = tuple((str(a), str(b)) for a, b in uncertainty.get("distance_pairs") or [])
    budget = UncertaintyBudget.from_dict(uncertainty["budget"])
    if frame_squareness is not None:
        opr_in_tool = np.linalg.inv(ur_to_matrix(tool_in_opr))
        positions = {p: np.mean([(euler_to_matrix(pose) @ opr_in_tool)[:3, 3] for pose in e["poses"]], axis=0)
                     for p, e in points.items()}
        transform = results.get("transform") or {}
        for term in squareness_terms(frame_squareness, positions, float(transform.get("lever") or 0.0),
                                     bool(transform.get("fitted"))):
            budget = budget.with_term(term)
    return CoverageCase(run, budget, distance_pairs=pairs, drift_cycles=uncertainty.get("drift_cycles"))
