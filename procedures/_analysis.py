"""What a finished run's samples mean: calibration records, ISO 9283 figures (stored as results).

All results are SI (metres, radians); reports convert.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from procedures._geometry import euler_to_matrix, matrix_to_euler, tcp_in_m, ur_to_matrix
from procedures._models import AngleCalibration, DisplacementCalibration
from procedures._plan import AXIS_INDEX
from procedures._science import ANGLE_COMPONENT, COMPONENTS
from procedures._truth import TruthLog

if TYPE_CHECKING:  # pragma: no cover
    from procedures._engine import RunEngine


def _truth(engine: RunEngine) -> TruthLog | None:
    sim = engine.station.model.simulation
    if sim is None or not sim.truth_log or not Path(sim.truth_log).is_file():
        return None
    return TruthLog.read(sim.truth_log)


def analyse(engine: RunEngine) -> dict[str, Any]:
    samples = engine.store.samples(engine.run_id)
    if isinstance(engine.procedure, (DisplacementCalibration, AngleCalibration)):
        return analyse_calibration(engine, samples)
    return analyse_iso(engine, samples)


def analyse_calibration(engine: RunEngine, samples) -> dict[str, Any]:
    displacement = isinstance(engine.procedure, DisplacementCalibration)
    kind = "displacement" if displacement else "angle"
    truth = _truth(engine)
    data: dict[str, list[dict]] = {}
    for sample in samples:
        if not sample.ok or sample.phase != "calibration":
            continue
        axis = sample.meta["axis"]
        component = axis if displacement else ANGLE_COMPONENT[axis]
        index = AXIS_INDEX[axis] + (0 if displacement else 3)
        entry = {"group": sample.meta["group"], "repeat": sample.meta["repeat"], "point": sample.meta["point"],
                 "nominal": sample.meta["nominal"], "measured": sample.solved["pose"][index],
                 "reference": sample.reference["value"]}
        if truth is not None and sample.t_measured is not None:
            state = truth.at(sample.t_measured)
            if state is not None:
                true_pose = list(state["opr_in_m"]["t"]) + list(state["opr_in_m"]["euler"])
                entry["true"] = true_pose[index]
        data.setdefault(component, []).append(entry)
    if not data:
        raise ValueError("no successful calibration samples to fit")
    references = ["laser interferometer"] if displacement else ["rotary table encoder"]
    fit = engine.science.fit_calibration(kind, data, {
        "run_id": engine.run_id, "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "references": [{"instrument": name, "components": sorted(data)} for name in references]})
    record_path = engine.params.record_path
    path = Path(record_path) if record_path else engine.store.run_dir(engine.run_id) / f"calibration-{kind}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(fit.record_json, encoding="utf-8")
    engine.store.update_run(engine.run_id, calibration_record_id=fit.record_id)
    return {
        "kind": f"{kind}_calibration", "record_path": str(path.resolve()), "record_id": fit.record_id,
        "data": data, "curves": fit.curves, "summary": fit.summary,
        "failed_samples": sum(1 for s in samples if not s.ok),
    }


def analyse_iso(engine: RunEngine, samples) -> dict[str, Any]:
    station = engine.station.model
    reference = station.frames.reference_tcp_pose
    opr_to_tool = ur_to_matrix(station.frames.tool_in_opr)
    truth = _truth(engine)

    def measured(sample) -> np.ndarray:
        return np.asarray((sample.corrected or sample.solved)["pose"], dtype=float)

    transform_samples = [s for s in samples if s.phase == "transform" and s.ok]
    fitted = np.eye(4)
    transform: dict[str, Any] = {"fitted": False}
    if len(transform_samples) >= 3:
        source = np.array([tcp_in_m(reference, s.commanded["tcp_pose"])[:3, 3] for s in transform_samples])
        target = np.array([measured(s)[:3] for s in transform_samples])
        rotation, translation, rms = engine.science.fit_rigid_transform(source, target)
        fitted[:3, :3], fitted[:3, 3] = rotation, translation
        transform = {"fitted": True, "rotation": rotation.tolist(), "translation": translation.tolist(),
                     "residual_rms": rms, "points": len(transform_samples)}

    order: list[str] = []
    for sample in samples:
        if sample.phase == "iso" and sample.label not in order:
            order.append(sample.label)
    points: dict[str, Any] = {}
    for label in order:
        mine = [s for s in samples if s.phase == "iso" and s.label == label and s.ok]
        if len(mine) < 2:
            points[label] = {"n": len(mine), "error": "fewer than 2 measured poses"}
            continue
        poses = np.array([matrix_to_euler(euler_to_matrix(measured(s)) @ opr_to_tool) for s in mine])
        commanded = matrix_to_euler(fitted @ tcp_in_m(reference, mine[0].commanded["tcp_pose"]) @ opr_to_tool)
        entry = {"n": len(mine), "stats": engine.science.iso_statistics(poses, commanded),
                 "poses": poses.tolist(), "commanded": commanded.tolist()}
        if truth is not None:
            states = [truth.at(s.t_measured) for s in mine if s.t_measured is not None]
            if states and all(state is not None for state in states):
                true = np.array([list(st["tool_in_m"]["t"]) + list(st["tool_in_m"]["euler"]) for st in states])
                entry["true_stats"] = engine.science.iso_statistics(true, commanded)
                entry["true_poses"] = true.tolist()
        points[label] = entry
    return {
        "kind": "iso9283", "order": order, "points": points, "transform": transform,
        "components": list(COMPONENTS),
        "compensation": [c.record_id for c in engine.compensators],
        "failed_samples": sum(1 for s in samples if not s.ok),
    }
