"""ISO 9283 pose stabilisation time and overshoot (7.4, 7.5), and the minimum positioning time (9),
measured while the robot moves.

Per step (one arrival): the robot goes to the pose before it in ISO 9283's cycle (P1 → P5 → P4 →
P3 → P2, so P1 is approached from P2), waits ``rest_s``, and moves to the step's pose at the step's
speed while the cameras stream from before the move starts until ``window_s`` after the controller
reports it done; the poses (compensated as the static kind does) give ``pose_stabilisation`` against
that done signal, with the band from the robot's specification (``band_um``, else the station's
``rated.stabilisation_band``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np
from pydantic import Field

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
    band_of,
    positioning_times,
    stabilisation_move,
    streams_of,
    summarise,
    truth_for,
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
from procedures.store import Sample

PointName = Literal["P1", "P2", "P3", "P4", "P5"]


def _p1() -> list[PointName]:
    return ["P1"]


class StabilisationParameters(DynamicParameters):
    points: list[PointName] = Field(default_factory=_p1, min_length=1, max_length=5,
                                    description="poses measured (ISO 9283's stabilisation test: P1; P1…P5 allowed)")
    band_um: float | None = Field(None, gt=0, le=10000, description="stabilisation band, µm (the manufacturer's); "
                                  "null: the station's rated.stabilisation_band, else 10 µm (recorded as assumed)")
    window_s: float = Field(0.8, gt=0, le=30, description="s streamed after the controller's done signal (the "
                            "longest wait for the pose to settle)")


class Iso9283Stabilisation(ProcedureBase):
    procedure: Literal["iso9283_stabilisation"]
    parameters: StabilisationParameters = Field(default_factory=StabilisationParameters)


def _previous(label: str) -> str:
    return CYCLE_ORDER[(CYCLE_ORDER.index(label) - 1) % len(CYCLE_ORDER)]


class Iso9283StabilisationKind:
    """Steps ``stab/s100/c000/P1``: per speed, per cycle, per point one streamed arrival."""

    name = "iso9283_stabilisation"
    parameters = StabilisationParameters
    file_model = Iso9283Stabilisation
    result_shape = ResultShape.STABILISATION
    iso_test_conditions = False
    measures_in_motion = True
    history_figures = ()

    def plan(self, params: StabilisationParameters, station: StationFile) -> list[Step]:
        steps: list[Step] = []
        order = [p for p in CYCLE_ORDER if p in params.points]
        for speed in params.speeds_percent:
            for cycle in range(params.cycles):
                for label in order:
                    start = cube_point(params, _previous(label))
                    steps.append(robot_step(len(steps), f"stab/s{speed:g}/c{cycle:03d}/{label}", "stabilisation",
                                            station, cube_point(params, label), start, label,
                                            {"cycle": cycle, "point": label, "speed_percent": float(speed),
                                             "from": _previous(label)}))
        return steps

    def devices(self, params: StabilisationParameters) -> tuple[DeviceRole, ...]:
        return ("robot",)

    def applies_compensation(self, params: StabilisationParameters) -> bool:
        return params.apply_compensation

    def move(self, step: Step, params: StabilisationParameters, ctx: StepContext) -> None:
        start_session(ctx, params)
        go_to(ctx, step.via[0])

    def measure(self, step: Step, params: StabilisationParameters, ctx: StepContext) -> Reading:
        ctx.wait(params.rest_s)
        target = np.asarray(step.robot_target(), dtype=float)
        speed, acceleration = motion_of(ctx.station, params, step.meta["speed_percent"])

        def motion() -> None:
            ctx.robot.move_linear(target, speed, acceleration, timeout=params.move_timeout_s)

        # wherever the motion ends, the next step moves from where it is
        ctx.session_state(DynamicSession).last_tcp = None
        record = ctx.stream_motion(step, motion, rate_hz=params.rate_hz, exposure_s=params.exposure_s,
                                   hold_s=params.window_s, target_in_m=step.meta["position_in_m"],
                                   direction=approach_direction(step))
        ctx.session_state(DynamicSession).last_tcp = list(step.robot_target())
        simulation = ctx.station.simulation
        record.meta["truth_log"] = simulation.truth_log if simulation is not None else None
        record.meta.update({"speed": speed, "acceleration": acceleration})
        problem = stream_problem(record, params)
        figures: dict[str, Any] = {"speed": speed, "acceleration": acceleration}
        if problem is None:
            band, _ = band_of(params, ctx.station)
            try:
                move = stabilisation_move(record, ur_to_matrix(ctx.station.frames.tool_in_opr), band, None)
                figures.update({k: move[k] for k in ("stabilisation_time", "overshoot", "t_signal")})
            except ValueError as exc:  # ISO9283Error: a record the function refuses
                problem = f"stabilisation: {exc}"
        return stream_reading(step, params, ctx, record, figures, problem)

    def analyse(self, samples: Sequence[Sample], params: StabilisationParameters, ctx: AnalysisContext) -> Analysis:
        return Analysis(results=analyse_stabilisation(samples, params, ctx))

    def title(self, parameters: Mapping[str, Any], results: Mapping[str, Any] | None) -> str:
        return settings_title("ISO 9283 pose stabilisation", parameters)


def analyse_stabilisation(samples: Sequence[Sample], params: StabilisationParameters,
                          ctx: AnalysisContext) -> dict[str, Any]:
    """Per move, per (point, speed) and the minimum positioning time; SI, with U and the truth's."""
    band, band_source = band_of(params, ctx.station)
    opr_to_tool = ur_to_matrix(ctx.station.frames.tool_in_opr)
    records = streams_of(ctx, samples)
    truths = truths_of(ctx.station.simulation)
    moves: list[dict[str, Any]] = []
    by_speed: dict[str, list[Any]] = {}
    for sample in samples:
        record = records.get(sample.step_index)
        if record is None or not sample.ok:
            continue
        meta = sample.meta or {}
        try:
            move = stabilisation_move(record, opr_to_tool, band, truth_for(truths, record))
        except ValueError as exc:
            moves.append({"step": sample.step_index, "key": sample.step_key, "error": str(exc)})
            continue
        move.update({"step": sample.step_index, "key": sample.step_key, "point": meta.get("point"),
                     "cycle": meta.get("cycle"), "speed_percent": meta.get("speed_percent"),
                     "speed": record.meta.get("speed")})
        moves.append(move)
        by_speed.setdefault(f"{meta.get('speed_percent'):g} %", []).append(record)
    groups: dict[tuple[str, float], list[dict[str, Any]]] = {}
    for move in moves:
        if "error" not in move:
            groups.setdefault((move["point"], move["speed_percent"]), []).append(move)
    settings = []
    for (point, speed), mine in groups.items():
        settings.append({"point": point, "speed_percent": speed, "speed": mine[0].get("speed"), "cycles": len(mine),
                         "stabilisation_time": summarise(mine, "stabilisation_time"),
                         "overshoot": summarise(mine, "overshoot")})
    # The report plots the first cycle of each setting; the rest keep their figures but not their series.
    plotted = {(m["point"], m["speed_percent"]) for m in moves if "error" not in m}
    for move in moves:
        key = (move.get("point"), move.get("speed_percent"))
        if key in plotted and "error" not in move:
            plotted.discard(key)
        else:
            move.pop("series", None)
            if move.get("true"):
                move["true"].pop("series", None)
    return {"kind": "iso9283_stabilisation", "band": band, "band_source": band_source, "settings": settings,
            "moves": moves, "positioning_time": positioning_times(by_speed, opr_to_tool, band),
            "failed": [s.step_key for s in samples if not s.ok], "simulated": bool(truths),
            "uncertainty": {"coverage_factor": 2.0, "covers": ["stream noise (from the settled tail)",
                                                                "frame period (interpolation of the crossing)"],
                            "not_covered": ["compensation residual (a slowly varying error: common to the "
                                            "attained pose and the excursion)", "clock fit", "motion blur"]}}


KIND = Iso9283StabilisationKind()
