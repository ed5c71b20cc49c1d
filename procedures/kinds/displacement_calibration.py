"""Displacement calibration (paper §3.4): the robot steps the OPR along each axis of M; the laser
interferometer, aligned to that axis and zeroed at each group's first point, is the reference.

Writes a calibration record with one compensation curve per axis (components x, y, z).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from procedures._geometry import translated_in_frame
from procedures._models import StationFile, Vec3
from procedures._report_sections import calibration_results_html
from procedures._store import Sample
from procedures.kinds._calibration import analyse_calibration, calibration_summary_lines, inclusive_range
from procedures.kinds._parameters import AxisName, MotionParameters, ProcedureBase, all_axes
from procedures.kinds._protocol import Analysis, AnalysisContext, DeviceRole, Reading, Step, StepContext
from procedures.kinds._setups import InterferometerAligned

AXIS_INDEX = {"x": 0, "y": 1, "z": 2}


def _paper_group_offsets() -> list[list[float]]:
    return [[0.0, 0.0, 0.0], [0.5, 0.5, 0.5], [-0.5, -0.5, -0.5]]


class DisplacementParameters(MotionParameters):
    axes: list[AxisName] = Field(default_factory=all_axes, min_length=1)
    start_mm: float = Field(0.0, description="first calibration point along the axis, mm")
    stop_mm: float = Field(70.0, description="last calibration point (inclusive), mm")
    step_mm: float = Field(5.0, gt=0, description="spacing of the points, mm")
    repeats: int = Field(3, ge=1, le=100, description="passes over the points per group")
    groups: int = Field(3, ge=1, le=20, description="groups, each from its own start pose")
    group_start_offsets_mm: list[Vec3] = Field(
        default_factory=_paper_group_offsets,
        description="per group, offset (mm, in M) of the whole line from M's origin",
    )
    interferometer_average_s: float = Field(0.5, gt=0, le=60, description="averaging window, s")
    record_path: str | None = Field(
        None, description="where to write the calibration record (default: in the run folder)"
    )

    @model_validator(mode="after")
    def _consistent(self) -> DisplacementParameters:
        if self.stop_mm <= self.start_mm:
            raise ValueError(f"stop_mm ({self.stop_mm}) must be above start_mm ({self.start_mm})")
        if len(self.group_start_offsets_mm) != self.groups:
            raise ValueError(f"groups is {self.groups} but group_start_offsets_mm has "
                             f"{len(self.group_start_offsets_mm)} entries: expected one offset per group")
        if len(set(self.axes)) != len(self.axes):
            raise ValueError(f"axes repeat an axis: {self.axes}")
        return self


class DisplacementCalibration(ProcedureBase):
    procedure: Literal["displacement_calibration"]
    parameters: DisplacementParameters = Field(default_factory=DisplacementParameters)


class DisplacementCalibrationKind:
    """Per axis, group and repeat, the points ``start_mm … stop_mm`` along the axis from the group's start."""

    name = "displacement_calibration"
    parameters = DisplacementParameters
    file_model = DisplacementCalibration

    def plan(self, params: DisplacementParameters, station: StationFile) -> list[Step]:
        values = inclusive_range(params.start_mm, params.stop_mm, params.step_mm) * 1e-3
        steps: list[Step] = []
        for axis in params.axes:
            k = AXIS_INDEX[axis]
            setup = InterferometerAligned(axis)
            for g, offset_mm in enumerate(params.group_start_offsets_mm):
                offset = np.asarray(offset_mm) * 1e-3
                for r in range(params.repeats):
                    for i, value in enumerate(values):
                        position = offset.copy()
                        position[k] += value
                        steps.append(Step(
                            index=len(steps), key=f"disp/{axis}/g{g}/r{r}/p{i:02d}", phase="calibration",
                            setup=setup,
                            tcp_pose=translated_in_frame(station.frames.reference_tcp_pose, position).tolist(),
                            label=f"{axis}={value * 1e3:g} mm",
                            meta={"axis": axis, "group": g, "repeat": r, "point": i, "nominal": float(position[k]),
                                  "group_start": float(offset[k] + values[0]),
                                  "zero_interferometer": r == 0 and i == 0},
                        ))
        return steps

    def devices(self, params: DisplacementParameters) -> tuple[DeviceRole, ...]:
        return ("robot", "interferometer")

    def applies_compensation(self, params: DisplacementParameters) -> bool:
        return False

    def move(self, step: Step, params: DisplacementParameters, ctx: StepContext) -> None:
        ctx.move_robot(step.robot_target())

    def measure(self, step: Step, params: DisplacementParameters, ctx: StepContext) -> Reading:
        ctx.settle()
        interferometer = ctx.interferometer
        if step.meta.get("zero_interferometer"):
            interferometer.zero()
        duration = params.interferometer_average_s
        reading = float(interferometer.average(duration, timeout=duration + 10.0))
        # The reference is where the group's line starts (nominal) plus the displacement since its zero.
        reference = {"interferometer_m": reading, "value": step.meta["group_start"] + reading,
                     "robot_tcp_pose": [float(v) for v in ctx.robot.tcp_pose()]}
        return Reading(pose=ctx.measure_pose(step), reference=reference)

    def analyse(self, samples: Sequence[Sample], params: DisplacementParameters, ctx: AnalysisContext) -> Analysis:
        return analyse_calibration(samples, ctx, kind="displacement", component_of_axis={a: a for a in "xyz"},
                                   reference_instrument="laser interferometer", record_path=params.record_path)

    def report_html(self, results: Mapping[str, Any]) -> str:
        return calibration_results_html(results)

    def summary_lines(self, results: Mapping[str, Any]) -> list[str]:
        return calibration_summary_lines(results)


KIND = DisplacementCalibrationKind()
