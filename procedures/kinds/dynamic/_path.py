"""ISO 9283 path accuracy and repeatability (8.2, 8.3), cornering deviations (8.5) and path velocity
(8.6), measured while the robot moves.

The path lies in the cube's diagonal plane (the plane of P2…P5): a line P2 → P3 → P4 with a corner at
P3 (``move_path``, blend ``corner_blend_mm``, 0: the commanded sharp corner) and a circle about P1
(two ``movec`` half circles), each streamed at every speed (% of the rated speed) for ``cycles``
cycles. A transform pass over P1…P5 first (settled poses, as the static kind's) fits the robot↔M
transform, so the commanded path is compared with the measured one in the instrument's frame.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np
from pydantic import Field

from procedures.kinds._conditions import SessionRecord
from procedures.kinds._parameters import ProcedureBase
from procedures.kinds._protocol import (
    Analysis,
    AnalysisContext,
    DeviceRole,
    Reading,
    ResultShape,
    Step,
    StepContext,
)
from procedures.kinds.dynamic._analysis import (
    circle_command,
    commanded_tool,
    compensation_position_rms,
    corner_figures,
    fitted_frame,
    linear_command,
    middle_of_leg,
    path_figures,
    rest_noise,
    streams_of,
    tool_poses,
    true_tool_path,
    truth_for,
    velocity_figures,
)
from procedures.kinds.dynamic._plan import (
    CYCLE_ORDER,
    DynamicParameters,
    DynamicSession,
    approach_direction,
    cube_point,
    go_to,
    motion_of,
    robot_step,
    settings_title,
    start_session,
    stream_problem,
    stream_reading,
)
from procedures.kinds.dynamic._truth import truths_of
from procedures.station import StationFile, ur_to_matrix
from procedures.store import Reference, Sample, as_pose

LINE = ("P2", "P3", "P4")  # the corner at P3: 90° in the diagonal plane


class PathParameters(DynamicParameters):
    transform_step: bool = Field(True, description="measure P1…P5 settled first and fit the robot↔M transform "
                                 "(without it AT holds the robot's mounting in M)")
    corner_blend_mm: float = Field(0.0, ge=0, le=50, description="blend radius at the corner P3, mm (0: the "
                                   "commanded sharp corner of ISO 9283 8.5)")
    circle_radius_mm: float = Field(15.0, gt=0, le=500, description="radius of the circle about P1 in the "
                                    "diagonal plane, mm")
    calculation_points: int = Field(20, ge=3, le=1000, description="calculation points per line leg (the circle "
                                    "has twice as many)")
    hold_s: float = Field(0.2, ge=0, le=30, description="s streamed after the controller's done signal")


class Iso9283Path(ProcedureBase):
    procedure: Literal["iso9283_path"]
    parameters: PathParameters = Field(default_factory=PathParameters)


def circle_points(params: PathParameters) -> dict[str, np.ndarray]:
    """Centre, start (= end), the two vias and the far point of the circle, in nominal M."""
    centre = cube_point(params, "P1")
    u = cube_point(params, "P3") - cube_point(params, "P2")
    u /= np.linalg.norm(u)
    w = cube_point(params, "P4") - cube_point(params, "P3")
    v = w - (w @ u) * u
    v /= np.linalg.norm(v)
    r = params.circle_radius_mm * 1e-3
    return {"centre": centre, "start": centre + r * u, "via_1": centre + r * v, "far": centre - r * u,
            "via_2": centre - r * v}


class Iso9283PathKind:
    """Phase ``transform`` (P1…P5 settled), then ``path``: per speed, per cycle, the line and the circle."""

    name = "iso9283_path"
    parameters = PathParameters
    file_model = Iso9283Path
    result_shape = ResultShape.PATH
    iso_test_conditions = False
    measures_in_motion = True
    history_figures = ()

    def plan(self, params: PathParameters, station: StationFile) -> list[Step]:
        steps: list[Step] = []
        if params.transform_step:
            for label in CYCLE_ORDER:
                steps.append(robot_step(len(steps), f"transform/{label}", "transform", station,
                                        cube_point(params, label), None, label, {"point": label}))
        circle = circle_points(params)
        for speed in params.speeds_percent:
            for cycle in range(params.cycles):
                common = {"cycle": cycle, "speed_percent": float(speed)}
                steps.append(robot_step(len(steps), f"path/s{speed:g}/c{cycle:03d}/line", "path", station,
                                        cube_point(params, LINE[2]), cube_point(params, LINE[0]), "line",
                                        {**common, "segment": "line"}, [cube_point(params, LINE[1])]))
                steps.append(robot_step(len(steps), f"path/s{speed:g}/c{cycle:03d}/circle", "path", station,
                                        circle["start"], circle["start"], "circle", {**common, "segment": "circle"},
                                        [circle["via_1"], circle["far"], circle["via_2"]]))
        return steps

    def devices(self, params: PathParameters) -> tuple[DeviceRole, ...]:
        return ("robot",)

    def applies_compensation(self, params: PathParameters) -> bool:
        return params.apply_compensation

    def move(self, step: Step, params: PathParameters, ctx: StepContext) -> None:
        start_session(ctx, params)
        go_to(ctx, step.via[0] if step.phase == "path" else step.robot_target())

    def measure(self, step: Step, params: PathParameters, ctx: StepContext) -> Reading:
        if step.phase == "transform":
            ctx.settle()
            reference = Reference(robot_tcp_pose=as_pose(ctx.robot.tcp_pose()))
            return Reading(pose=ctx.measure_pose(step), reference=reference,
                           session=ctx.session_state(SessionRecord).take())
        ctx.wait(params.rest_s)
        speed, acceleration = motion_of(ctx.station, params, step.meta["speed_percent"])
        vias = [np.asarray(p, dtype=float) for p in step.via[1:]]
        target = np.asarray(step.robot_target(), dtype=float)
        if step.meta["segment"] == "line":
            def motion() -> None:
                ctx.robot.move_path(np.array([vias[0], target]), speed, acceleration,
                                    [params.corner_blend_mm * 1e-3, 0.0], timeout=params.move_timeout_s)
        else:
            def motion() -> None:
                ctx.robot.move_circular(np.array([vias[0], vias[2]]), np.array([vias[1], target]), speed,
                                        acceleration, blend_radius=0.0, timeout=params.move_timeout_s)
        ctx.session_state(DynamicSession).last_tcp = None
        record = ctx.stream_motion(step, motion, rate_hz=params.rate_hz, exposure_s=params.exposure_s,
                                   hold_s=params.hold_s, target_in_m=step.meta["position_in_m"],
                                   direction=approach_direction(step))
        ctx.session_state(DynamicSession).last_tcp = list(step.robot_target())
        simulation = ctx.station.simulation
        record.meta["truth_log"] = simulation.truth_log if simulation is not None else None
        record.meta.update({"speed": speed, "acceleration": acceleration})
        return stream_reading(step, params, ctx, record, {"speed": speed, "acceleration": acceleration},
                              stream_problem(record, params))

    def analyse(self, samples: Sequence[Sample], params: PathParameters, ctx: AnalysisContext) -> Analysis:
        return Analysis(results=analyse_path(samples, params, ctx))

    def title(self, parameters: Mapping[str, Any], results: Mapping[str, Any] | None) -> str:
        return settings_title("ISO 9283 path characteristics", parameters)


def analyse_path(samples: Sequence[Sample], params: PathParameters, ctx: AnalysisContext) -> dict[str, Any]:
    """Per speed: AT/RT of both legs and the circle, CR/CO at P3, AV/RV/FV on leg 2; SI, U, truth."""
    opr_to_tool = ur_to_matrix(ctx.station.frames.tool_in_opr)
    truths = truths_of(ctx.station.simulation)
    fitted, mirror, transform = fitted_frame(ctx, samples, truths)
    records = streams_of(ctx, samples)
    u_comp = compensation_position_rms(ctx) if params.apply_compensation else None
    line = [commanded_tool(ctx, fitted, cube_point(params, p)) for p in LINE]
    circle = {k: commanded_tool(ctx, fitted, v) for k, v in circle_points(params).items()}
    settings = []
    speeds = list(dict.fromkeys(float((s.meta or {}).get("speed_percent", 0)) for s in samples if s.phase == "path"))
    for speed in speeds:
        entry: dict[str, Any] = {"speed_percent": speed}
        for segment in ("line", "circle"):
            mine = [s for s in samples if s.phase == "path" and s.ok and (s.meta or {}).get("segment") == segment
                    and float((s.meta or {}).get("speed_percent", 0)) == speed and s.step_index in records]
            measured = [tool_poses(records[s.step_index].pose, opr_to_tool) for s in mine]
            true_paths = [true_tool_path(records[s.step_index], truth_for(truths, records[s.step_index]), mirror,
                                         opr_to_tool) for s in mine]
            true = [p for p in true_paths if p is not None] if all(p is not None for p in true_paths) else None
            noise = [rest_noise(records[s.step_index], p) for s, p in zip(mine, measured)]
            sigma = float(np.nanmedian(noise)) if noise and np.any(np.isfinite(noise)) else float("nan")
            entry[f"{segment}_cycles"] = len(mine)
            entry[f"{segment}_noise_sigma"] = sigma
            if mine:
                entry["speed"] = records[mine[0].step_index].meta.get("speed")

            def u_position(n: int, sigma: float = sigma) -> float | None:
                if u_comp is None or not np.isfinite(sigma):
                    return None
                return float(2.0 * np.sqrt(u_comp**2 + sigma**2 / max(n, 1)))

            if len(mine) < 2:
                entry[segment] = {"error": f"{len(mine)} measured cycles (at least 2 needed)"}
                continue
            if segment == "line":
                points = params.calculation_points
                entry["leg_1"] = path_figures(linear_command(line[0], line[1], points), measured, true, u_position)
                entry["leg_2"] = path_figures(linear_command(line[1], line[2], points), measured, true, u_position)
                entry["corner"] = corner_figures(line[1], line[0], line[2], measured, true, u_position(1), sigma)
                commanded_speed = float(records[mine[0].step_index].meta.get("speed") or 0.0)
                cycles = [middle_of_leg(records[s.step_index].t, p, line[1], line[2]) for s, p in zip(mine, measured)]
                true_cycles = None if true is None else [
                    middle_of_leg(records[s.step_index].t, p, line[1], line[2]) for s, p in zip(mine, true)]
                entry["velocity"] = velocity_figures(cycles, commanded_speed, sigma, true_cycles)
            else:
                command, radius = circle_command(circle["centre"], circle["start"], circle["via_1"],
                                                 2 * params.calculation_points)
                figures = path_figures(command, measured, true, u_position)
                speed_m_s = float(records[mine[0].step_index].meta.get("speed") or 0.0)
                chord = speed_m_s / params.rate_hz
                figures["chord_sag"] = chord**2 / (8.0 * radius)  # how far a chord between samples lies inside
                entry["circle"] = figures
        settings.append(entry)
    return {"kind": "iso9283_path", "transform": transform, "settings": settings, "compensation_rms": u_comp,
            "failed": [s.step_key for s in samples if not s.ok], "simulated": bool(truths),
            "uncertainty": {"coverage_factor": 2.0,
                            "covers": ["stream noise", "compensation residual (AT_p, CR; the records' held-out "
                                       "RMS; no U without a record)"],
                            "not_covered": ["transform fit", "interferometer scale, environment, off-axis angles, "
                                            "frame squareness (the static ISO budget's other terms)", "clock fit",
                                            "motion blur", "chord sag on the circle (given as chord_sag)",
                                            "RT and orientation figures (noise is inside the figure)"]}}


KIND = Iso9283PathKind()
