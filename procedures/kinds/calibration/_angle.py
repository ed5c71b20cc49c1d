"""Angle calibration (paper §3.4): the OPR sits on the rotary table, whose axis is one of M's axes;
the table's encoder is the reference. The operator re-mounts the OPR per axis.

Writes a calibration record with one curve per angle (components a, b, c about x, y, z).

``approach: one`` reaches every angle turning positive (a pre-position ``overshoot_deg`` below it
where the table does not already come from below); ``both`` makes each repeat an ascending pass (+1)
and a descending one (−1). Samples record their direction.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np
from pydantic import Field, ValidationInfo, field_validator, model_validator

from instrument import COMPONENTS
from procedures.kinds._approach import Approach, approach_table, directions_of
from procedures.kinds._parameters import AxisName, MotionParameters, ProcedureBase, all_axes
from procedures.kinds._protocol import (
    Analysis,
    AnalysisContext,
    DeviceRole,
    Reading,
    ResultShape,
    Step,
    StepContext,
)
from procedures.kinds._setups import OprOnTable
from procedures.kinds.calibration._common import (
    analyse_calibration,
    check_calibration_size,
    check_record_path,
    inclusive_range,
    line_points,
)
from procedures.station import ANGLE_COMPONENT, StationFile
from procedures.store import Reference, Sample


def _paper_group_offsets() -> list[float]:
    return [0.0, 0.1, -0.1]


class AngleParameters(MotionParameters):
    axes: list[AxisName] = Field(default_factory=all_axes, min_length=1)
    start_deg: float = Field(-1.0, description="first table angle, degrees")
    stop_deg: float = Field(1.0, description="last table angle (inclusive), degrees")
    step_deg: float = Field(0.25, gt=0, description="spacing, degrees (at least 5 points per line)")
    repeats: int = Field(3, ge=1, le=100, description="passes over the angles per group (at least 2 for a new run)")
    groups: int = Field(3, ge=1, le=20)
    group_start_offsets_deg: list[float] = Field(
        default_factory=_paper_group_offsets, description="per group, offset of all angles, degrees"
    )
    table_speed_deg_s: float = Field(5.0, gt=0, le=360, description="rotary table speed, °/s")
    home_table: bool = Field(True, description="home the table before the first axis if it is not homed")
    approach: Approach = Field("one", description="one: every angle approached turning positive; both: each "
                               "repeat an ascending and a descending pass (approach from below and from above)")
    overshoot_deg: float = Field(0.05, gt=0, le=5, description="how far beyond an angle the table turns first to "
                                 "approach it from the wanted side, degrees")
    record_path: str | None = Field(
        None, description="where to write the calibration record: a path relative to the runs folder, without "
        "'..' (default: calibration-angle.json in the run's folder)"
    )

    _record_path = field_validator("record_path")(check_record_path)

    @model_validator(mode="after")
    def _consistent(self, info: ValidationInfo) -> AngleParameters:
        if self.stop_deg <= self.start_deg:
            raise ValueError(f"stop_deg ({self.stop_deg}) must be above start_deg ({self.start_deg})")
        if len(self.group_start_offsets_deg) != self.groups:
            raise ValueError(f"groups is {self.groups} but group_start_offsets_deg has "
                             f"{len(self.group_start_offsets_deg)} entries: expected one offset per group")
        if len(set(self.axes)) != len(self.axes):
            raise ValueError(f"axes repeat an axis: {self.axes}")
        check_calibration_size(line_points(self.start_deg, self.stop_deg, self.step_deg),
                               len(self.axes) * self.groups * len(directions_of(self.approach)), self.repeats,
                               "step_deg", info)
        return self


class AngleCalibration(ProcedureBase):
    procedure: Literal["angle_calibration"]
    parameters: AngleParameters = Field(default_factory=AngleParameters)


class AngleCalibrationKind:
    """Per axis, group and repeat, the table angles ``start_deg … stop_deg`` shifted by the group's offset."""

    name = "angle_calibration"
    parameters = AngleParameters
    file_model = AngleCalibration
    result_shape = ResultShape.CALIBRATION
    iso_test_conditions = False
    measures_in_motion = False
    history_figures = ()

    def plan(self, params: AngleParameters, station: StationFile) -> list[Step]:
        values = np.radians(inclusive_range(params.start_deg, params.stop_deg, params.step_deg))
        steps: list[Step] = []
        for axis in params.axes:
            setup = OprOnTable(axis, home_table=params.home_table, home_timeout_s=params.move_timeout_s)
            for g, offset_deg in enumerate(params.group_start_offsets_deg):
                for r in range(params.repeats):
                    for direction in directions_of(params.approach):
                        order = range(len(values)) if direction > 0 else range(len(values) - 1, -1, -1)
                        for i in order:
                            angle = float(values[i] + np.radians(offset_deg))
                            steps.append(Step(
                                index=len(steps), key=f"angle/{axis}/g{g}/r{r}/p{i:02d}" + ("" if direction > 0
                                                                                           else "/down"),
                                phase="calibration", setup=setup, table_angle=angle,
                                label=f"{axis}={np.degrees(angle):.4g}°" + ("" if direction > 0 else " ↓"),
                                meta={"axis": axis, "group": g, "repeat": r, "point": i, "nominal": angle,
                                      "approach": direction},
                            ))
        return steps

    def devices(self, params: AngleParameters) -> tuple[DeviceRole, ...]:
        return ("rotary_table",)

    def applies_compensation(self, params: AngleParameters) -> bool:
        return False

    def move(self, step: Step, params: AngleParameters, ctx: StepContext) -> None:
        approach_table(ctx, step, float(np.radians(params.table_speed_deg_s)), float(np.radians(params.overshoot_deg)))

    def measure(self, step: Step, params: AngleParameters, ctx: StepContext) -> Reading:
        ctx.settle()
        table_rad = float(ctx.table.position())
        # Only the angle about the table's axis is known: the OPR's position turns with the table.
        expected = {COMPONENTS.index(ANGLE_COMPONENT[step.meta["axis"]]): table_rad}
        return Reading(pose=ctx.measure_pose(step, expected=expected),
                       reference=Reference(value=table_rad, approach=step.meta.get("approach"),
                                           readings={"table_rad": table_rad}))

    def analyse(self, samples: Sequence[Sample], params: AngleParameters, ctx: AnalysisContext) -> Analysis:
        return analyse_calibration(samples, ctx, kind="angle", component_of_axis=ANGLE_COMPONENT,
                                   reference_instrument="rotary table encoder", record_path=params.record_path,
                                   params=params, approach=params.approach)

    def title(self, parameters: Mapping[str, Any], results: Mapping[str, Any] | None) -> str:
        return "Angle calibration of the optical pose reference"


KIND = AngleCalibrationKind()
