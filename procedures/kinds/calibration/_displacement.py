"""Displacement calibration (paper §3.4): the robot steps the OPR along each axis of M; the laser
interferometer, aligned to that axis and zeroed at each group's first point, is the reference.

Writes a calibration record with one compensation curve per axis (components x, y, z).

**The datum.** A reading means something only relative to the datum set by ``zero()`` at the
group's first point, and the interferometer loses it whenever its beam breaks or the head is
re-aimed (which every resume does). So a datum is trusted only within the session that set it
(``DisplacementSession``). A step whose group has no datum in this session — a resumed run, a failed pose
measured again, or a ``DatumLost``/``BeamInterrupted`` while reading — **re-establishes** it: the
robot returns to the group's first point, the interferometer is zeroed there, the robot goes back
to the step. Every sample records its datum (its reference's ``datum_set_at`` and ``datum_reestablished``)
and the run log says when one was re-established. A ``FeedGap`` or a lost feed connection (the
driver reconnects by itself) is read again after a back-off: the head keeps its count meanwhile, and
the driver says ``DatumLost`` if it did not. The robot never returns to a point exactly
(repeatability ~10 µm), so each datum is its own offset: the analysis treats the samples of each
datum as their own calibration group, whose offset the group alignment estimates.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from pydantic import Field, ValidationInfo, field_validator, model_validator

from drivers import DeviceConnectionError, DeviceFault
from drivers.interferometer import BeamInterrupted, FeedGap
from instrument.environment import AirConditions, AirConditionsError
from procedures.kinds._approach import Approach, approach_on_line, directions_of, note_line_position, robot_pose_in_m
from procedures.kinds._environment import environment_record
from procedures.kinds._parameters import AxisName, MotionParameters, ProcedureBase, all_axes, retry_wait
from procedures.kinds._protocol import (
    Analysis,
    AnalysisContext,
    DeviceRole,
    Reading,
    ResultShape,
    Step,
    StepContext,
)
from procedures.kinds._references import compensate
from procedures.kinds._setups import InterferometerAligned
from procedures.kinds.calibration._common import (
    analyse_calibration,
    check_calibration_size,
    check_record_path,
    inclusive_range,
    line_points,
)
from procedures.station import StationFile, Vec3, translated_in_frame
from procedures.store import Reference, Sample, as_pose

AXIS_INDEX = {"x": 0, "y": 1, "z": 2}
READ_ATTEMPTS = 3  # interferometer readings per step (a lost datum or a feed gap in between is repaired)
ZERO_ATTEMPTS = 3  # zero() attempts while the beam is still broken


@dataclass(frozen=True)
class Datum:
    """The interferometer's datum of one group, set in this session (``set_at``: host time, s)."""

    set_at: float
    reestablished: bool


@dataclass
class DisplacementSession:
    """What one session of a displacement calibration knows: the datum of each (axis, group) it set."""

    datums: dict[tuple[str, int], Datum] = field(default_factory=dict)


def _paper_group_offsets() -> list[list[float]]:
    return [[0.0, 0.0, 0.0], [0.5, 0.5, 0.5], [-0.5, -0.5, -0.5]]


class DisplacementParameters(MotionParameters):
    axes: list[AxisName] = Field(default_factory=all_axes, min_length=1)
    start_mm: float = Field(0.0, description="first calibration point along the axis, mm")
    stop_mm: float = Field(70.0, description="last calibration point (inclusive), mm")
    step_mm: float = Field(5.0, gt=0, description="spacing of the points, mm (at least 5 points per line)")
    repeats: int = Field(3, ge=1, le=100, description="passes over the points per group (at least 2 for a new run)")
    groups: int = Field(3, ge=1, le=20, description="groups, each from its own start pose")
    group_start_offsets_mm: list[Vec3] = Field(
        default_factory=_paper_group_offsets,
        description="per group, offset (mm, in M) of the whole line from M's origin",
    )
    interferometer_average_s: float = Field(0.5, gt=0, le=60, description="averaging window, s")
    wavelength_compensation: bool = Field(
        True, description="compensate each reading for the air read from the head's environmental unit (modified "
        "Edlén); false: the head's nominal air is taken as it is (a larger scale uncertainty, recorded)")
    approach: Approach = Field("one", description="one: every point approached from below; both: each repeat "
                               "an ascending and a descending pass (approach from below and from above)")
    overshoot_mm: float = Field(1.0, gt=0, le=20, description="how far beyond a point the robot goes first to "
                                "approach it from the wanted side, mm")
    record_path: str | None = Field(
        None, description="where to write the calibration record: a path relative to the runs folder, without "
        "'..' (default: calibration-displacement.json in the run's folder)"
    )

    _record_path = field_validator("record_path")(check_record_path)

    @model_validator(mode="after")
    def _consistent(self, info: ValidationInfo) -> DisplacementParameters:
        if self.stop_mm <= self.start_mm:
            raise ValueError(f"stop_mm ({self.stop_mm}) must be above start_mm ({self.start_mm})")
        if len(self.group_start_offsets_mm) != self.groups:
            raise ValueError(f"groups is {self.groups} but group_start_offsets_mm has "
                             f"{len(self.group_start_offsets_mm)} entries: expected one offset per group")
        if len(set(self.axes)) != len(self.axes):
            raise ValueError(f"axes repeat an axis: {self.axes}")
        check_calibration_size(line_points(self.start_mm, self.stop_mm, self.step_mm),
                               len(self.axes) * self.groups * len(directions_of(self.approach)),
                               self.repeats, "step_mm", info)
        return self


class DisplacementCalibration(ProcedureBase):
    procedure: Literal["displacement_calibration"]
    parameters: DisplacementParameters = Field(default_factory=DisplacementParameters)


class DisplacementCalibrationKind:
    """Per axis, group and repeat, the points ``start_mm … stop_mm`` along the axis from the group's start."""

    name = "displacement_calibration"
    parameters = DisplacementParameters
    file_model = DisplacementCalibration
    result_shape = ResultShape.CALIBRATION
    iso_test_conditions = False
    measures_in_motion = False
    history_figures = ()

    def plan(self, params: DisplacementParameters, station: StationFile) -> list[Step]:
        values = inclusive_range(params.start_mm, params.stop_mm, params.step_mm) * 1e-3
        steps: list[Step] = []
        for axis in params.axes:
            k = AXIS_INDEX[axis]
            setup = InterferometerAligned(axis)
            for g, offset_mm in enumerate(params.group_start_offsets_mm):
                offset = np.asarray(offset_mm) * 1e-3
                for r in range(params.repeats):
                    for direction in directions_of(params.approach):
                        order = range(len(values)) if direction > 0 else range(len(values) - 1, -1, -1)
                        for i in order:
                            position = offset.copy()
                            position[k] += values[i]
                            before = position.copy()
                            before[k] -= direction * params.overshoot_mm * 1e-3
                            steps.append(Step(
                                index=len(steps), key=f"disp/{axis}/g{g}/r{r}/p{i:02d}" + ("" if direction > 0
                                                                                          else "/down"),
                                phase="calibration", setup=setup,
                                tcp_pose=translated_in_frame(station.frames.reference_tcp_pose, position).tolist(),
                                label=f"{axis}={values[i] * 1e3:g} mm" + ("" if direction > 0 else " ↓"),
                                meta={"axis": axis, "group": g, "repeat": r, "point": i,
                                      "nominal": float(position[k]), "group_start": float(offset[k] + values[0]),
                                      "zero_interferometer": r == 0 and i == 0 and direction > 0,
                                      "approach": direction},
                                via=(translated_in_frame(station.frames.reference_tcp_pose, before).tolist(),),
                            ))
        return steps

    def devices(self, params: DisplacementParameters) -> tuple[DeviceRole, ...]:
        return ("robot", "interferometer")

    def applies_compensation(self, params: DisplacementParameters) -> bool:
        return False

    def move(self, step: Step, params: DisplacementParameters, ctx: StepContext) -> None:
        approach_on_line(ctx, step, AXIS_INDEX[step.meta["axis"]], params.overshoot_mm * 1e-3)

    def measure(self, step: Step, params: DisplacementParameters, ctx: StepContext) -> Reading:
        ctx.settle()
        datum = self._datum(step, params, ctx)
        duration = params.interferometer_average_s
        for attempt in range(READ_ATTEMPTS):
            try:
                reading = float(ctx.interferometer.average(duration, timeout=duration + 10.0))
                # The air right after the window (the unit reads once a second; the air drifts by tenths of
                # a kelvin an hour): a stale reading is a FeedGap, read again with the displacement.
                environment = ctx.interferometer.environment() if params.wavelength_compensation else None
                break
            except BeamInterrupted as exc:  # DatumLost too: the count is gone, so is the datum
                if attempt == READ_ATTEMPTS - 1:
                    raise
                ctx.log("datum_lost", f"{step.key}: {exc}")
                ctx.wait(retry_wait(params, attempt))
                datum = self._reestablish(step, params, ctx, why=f"the datum was lost ({exc.cause})")
            except (FeedGap, DeviceConnectionError) as exc:
                # Samples missing from the window, or the feed's connection down (the driver reconnects
                # by itself): the head keeps counting, so the datum stands (a DatumLost would say otherwise).
                if attempt == READ_ATTEMPTS - 1:
                    raise
                ctx.log("feed_gap", f"{step.key}: {exc}; reading again")
                ctx.wait(retry_wait(params, attempt))
        displacement, wavelength = reading, None
        if environment is not None:
            optics = ctx.interferometer.optics
            air = AirConditions(environment.air_temperature_k, environment.pressure_pa, environment.relative_humidity,
                                optics.air_co2)
            try:
                compensation = compensate(reading, air, optics)
            except AirConditionsError as exc:
                raise DeviceFault(ctx.interferometer.name, "environment",
                                  f"the air read cannot be compensated for: {exc}") from None
            displacement, wavelength = compensation.apply(reading), compensation.as_record()
        # The reference is where the group's line starts (nominal) plus the displacement since its zero.
        reference = Reference(value=step.meta["group_start"] + displacement, approach=step.meta.get("approach"),
                              environment=None if environment is None else environment_record(environment),
                              robot_tcp_pose=as_pose(ctx.robot.tcp_pose()),
                              readings={"interferometer_raw_m": reading, "interferometer_m": displacement,
                                        "wavelength_compensation": wavelength, "datum_set_at": datum.set_at,
                                        "datum_reestablished": datum.reestablished})
        expected = robot_pose_in_m(ctx.station.frames.reference_tcp_pose, step.robot_target())
        return Reading(pose=ctx.measure_pose(step, expected=dict(enumerate(expected))), reference=reference)

    def _datum(self, step: Step, params: DisplacementParameters, ctx: StepContext) -> Datum:
        """The datum of the step's group in this session: set here at the group's first point, kept
        from an earlier step of this session, or re-established (see the module docstring)."""
        datums = ctx.session_state(DisplacementSession).datums
        key = (step.meta["axis"], step.meta["group"])
        if step.meta.get("zero_interferometer"):
            datums[key] = Datum(self._zero(params, ctx), reestablished=False)
        elif key not in datums:
            return self._reestablish(step, params, ctx, why="no datum in this session (a resumed run or a pose "
                                                            "measured again)")
        return datums[key]

    def _reestablish(self, step: Step, params: DisplacementParameters, ctx: StepContext, *, why: str) -> Datum:
        """Back to the group's first point, zero there, back to the step (settled each time)."""
        along = np.zeros(3)
        along[AXIS_INDEX[step.meta["axis"]]] = step.meta["group_start"] - step.meta["nominal"]
        # Every pose of a line has the reference orientation, so this lands on the group's first point.
        ctx.move_robot(translated_in_frame(step.robot_target(), along).tolist())
        ctx.settle()
        datum = Datum(self._zero(params, ctx), reestablished=True)
        ctx.session_state(DisplacementSession).datums[(step.meta["axis"], step.meta["group"])] = datum
        ctx.log("datum", f"{step.meta['axis']} group {step.meta['group']}: datum re-established at the group's "
                         f"first point before {step.key}: {why}")
        note_line_position(ctx, step, step.meta["group_start"])
        approach_on_line(ctx, step, AXIS_INDEX[step.meta["axis"]], params.overshoot_mm * 1e-3)
        ctx.settle()
        return datum

    @staticmethod
    def _zero(params: DisplacementParameters, ctx: StepContext) -> float:
        """``zero()``, retried while the beam is still broken; returns when the datum was set (host time)."""
        for attempt in range(ZERO_ATTEMPTS):
            try:
                ctx.interferometer.zero()
                return time.time()
            except BeamInterrupted:
                if attempt == ZERO_ATTEMPTS - 1:
                    raise
                ctx.wait(retry_wait(params, attempt))
        raise AssertionError("unreachable")

    def analyse(self, samples: Sequence[Sample], params: DisplacementParameters, ctx: AnalysisContext) -> Analysis:
        return analyse_calibration(samples, ctx, kind="displacement", component_of_axis={a: a for a in "xyz"},
                                   reference_instrument="laser interferometer", record_path=params.record_path,
                                   params=params, approach=params.approach,
                                   wavelength_compensation=params.wavelength_compensation)

    def title(self, parameters: Mapping[str, Any], results: Mapping[str, Any] | None) -> str:
        return "Displacement calibration of the optical pose reference"


KIND = DisplacementCalibrationKind()
