"""ISO 9283 pose repeatability and accuracy (paper §4): P1…P5 on the cube's diagonal plane, visited
P1 → P5 → P4 → P3 → P2 for ``cycles`` cycles, after an optional end-effector transform pass.

Each attained OPR pose (compensated with the station's records when asked) is turned into the tool
point's pose; RP and AP per point come from ``instrument.iso9283``, and in simulation the same
figures from the ground-truth log.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np
from pydantic import Field

from instrument.iso9283 import iso_cube_points
from procedures._geometry import euler_to_matrix, matrix_to_euler, tcp_in_m, translated_in_frame, ur_to_matrix
from procedures._models import StationFile, Vec3
from procedures._report_sections import iso_results_html
from procedures._science import COMPONENTS
from procedures._store import Sample
from procedures.kinds._parameters import MotionParameters, ProcedureBase
from procedures.kinds._protocol import Analysis, AnalysisContext, DeviceRole, Reading, Step, StepContext
from procedures.kinds._setups import OprOnRobot


def _paper_cube_center() -> list[float]:
    return [0.035, 0.035, 0.035]


class IsoParameters(MotionParameters):
    cube_center_m: Vec3 = Field(default_factory=_paper_cube_center, description="cube centre in M, metres")
    cube_edge_m: float = Field(0.07, gt=0, le=2.0, description="cube edge, metres")
    cycles: int = Field(30, ge=2, le=10000, description="ISO 9283 cycles (the standard asks for 30)")
    transform_step: bool = Field(True, description="measure the cube once first and fit the robot↔M transform")
    apply_compensation: bool = Field(True, description="correct poses with the calibration record in force")


class Iso9283Repeatability(ProcedureBase):
    procedure: Literal["iso9283_repeatability"]
    parameters: IsoParameters = Field(default_factory=IsoParameters)


class Iso9283RepeatabilityKind:
    """The transform pass (phase ``transform``), then the cycles (phase ``iso``)."""

    name = "iso9283_repeatability"
    parameters = IsoParameters
    file_model = Iso9283Repeatability

    def plan(self, params: IsoParameters, station: StationFile) -> list[Step]:
        cube = iso_cube_points(np.asarray(params.cube_center_m, dtype=float), float(params.cube_edge_m))
        points = list(zip(cube.order, cube.positions_in_order()))
        reference = station.frames.reference_tcp_pose
        setup = OprOnRobot()
        passes = ([("transform", 0)] if params.transform_step else []) + [("iso", c) for c in range(params.cycles)]
        steps: list[Step] = []
        for phase, cycle in passes:
            for label, point in points:
                steps.append(Step(
                    index=len(steps), key=f"{phase}/c{cycle:03d}/{label}", phase=phase, setup=setup,
                    tcp_pose=translated_in_frame(reference, point).tolist(), label=label,
                    meta={"cycle": cycle, "point": label, "position_in_m": [float(v) for v in point]},
                ))
        return steps

    def devices(self, params: IsoParameters) -> tuple[DeviceRole, ...]:
        return ("robot",)

    def applies_compensation(self, params: IsoParameters) -> bool:
        return params.apply_compensation

    def move(self, step: Step, params: IsoParameters, ctx: StepContext) -> None:
        ctx.move_robot(step.robot_target())

    def measure(self, step: Step, params: IsoParameters, ctx: StepContext) -> Reading:
        ctx.settle()
        reference = {"robot_tcp_pose": [float(v) for v in ctx.robot.tcp_pose()]}
        return Reading(pose=ctx.measure_pose(step), reference=reference)

    def analyse(self, samples: Sequence[Sample], params: IsoParameters, ctx: AnalysisContext) -> Analysis:
        return Analysis(results=analyse_iso(samples, ctx))

    def report_html(self, results: Mapping[str, Any]) -> str:
        return iso_results_html(results)

    def summary_lines(self, results: Mapping[str, Any]) -> list[str]:
        from procedures._report_sections import iso_summary_lines  # here, not above: the import block is shared

        return iso_summary_lines(results)


def _measured(sample: Sample) -> np.ndarray:
    best = sample.corrected or sample.solved or {}
    return np.asarray(best["pose"], dtype=float)


def _commanded_tcp(sample: Sample) -> list[float]:
    return (sample.commanded or {})["tcp_pose"]


def analyse_iso(samples: Sequence[Sample], ctx: AnalysisContext) -> dict[str, Any]:
    """RP and AP of the tool point per ISO point, after the robot↔M transform fitted on the transform pass."""
    reference = ctx.station.frames.reference_tcp_pose
    opr_to_tool = ur_to_matrix(ctx.station.frames.tool_in_opr)

    transform_samples = [s for s in samples if s.phase == "transform" and s.ok]
    fitted = np.eye(4)
    transform: dict[str, Any] = {"fitted": False}
    if len(transform_samples) >= 3:
        source = np.array([tcp_in_m(reference, _commanded_tcp(s))[:3, 3] for s in transform_samples])
        target = np.array([_measured(s)[:3] for s in transform_samples])
        rotation, translation, rms = ctx.science.fit_rigid_transform(source, target)
        fitted[:3, :3], fitted[:3, 3] = rotation, translation
        transform = {"fitted": True, "rotation": rotation.tolist(), "translation": translation.tolist(),
                     "residual_rms": rms, "points": len(transform_samples)}

    order: list[str] = []
    for sample in samples:
        if sample.phase == "iso" and sample.label not in order and sample.label is not None:
            order.append(sample.label)
    points: dict[str, Any] = {}
    for label in order:
        mine = [s for s in samples if s.phase == "iso" and s.label == label and s.ok]
        if len(mine) < 2:
            points[label] = {"n": len(mine), "error": "fewer than 2 measured poses"}
            continue
        poses = np.array([matrix_to_euler(euler_to_matrix(_measured(s)) @ opr_to_tool) for s in mine])
        commanded = matrix_to_euler(fitted @ tcp_in_m(reference, _commanded_tcp(mine[0])) @ opr_to_tool)
        entry = {"n": len(mine), "stats": ctx.science.iso_statistics(poses, commanded),
                 "poses": poses.tolist(), "commanded": commanded.tolist()}
        if ctx.truth is not None:
            states = [ctx.truth.at(s.t_measured) for s in mine if s.t_measured is not None]
            if states and all(state is not None for state in states):
                true = np.array([list(st["tool_in_m"]["t"]) + list(st["tool_in_m"]["euler"])
                                 for st in states if st is not None])
                entry["true_stats"] = ctx.science.iso_statistics(true, commanded)
                entry["true_poses"] = true.tolist()
        points[label] = entry
    return {
        "kind": "iso9283", "order": order, "points": points, "transform": transform,
        "components": list(COMPONENTS),
        "compensation": [c.record_id for c in ctx.compensators],
        "failed_samples": sum(1 for s in samples if not s.ok),
    }


KIND = Iso9283RepeatabilityKind()
