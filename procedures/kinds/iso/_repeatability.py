"""ISO 9283 pose repeatability and accuracy (paper §4): P1…P5 on the cube's diagonal plane, visited
P1 → P5 → P4 → P3 → P2 for ``cycles`` cycles, after an optional end-effector transform pass.

Each attained OPR pose (compensated with the station's records when asked) is turned into the tool
point's pose; RP and AP per point come from ``instrument.iso9283``, and in simulation the same
figures from the ground-truth log.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from procedures.kinds._approach import pose_directions, robot_pose_in_m
from procedures.kinds._conditions import SessionRecord, operator_of, robot_identity, set_payload, warm_up
from procedures.kinds._environment import environment_record, read_environment
from procedures.kinds._protocol import (
    Analysis,
    AnalysisContext,
    DeviceRole,
    Reading,
    ResultShape,
    Step,
    StepContext,
)
from procedures.kinds._setups import OprOnRobot
from procedures.kinds.iso._analysis import analyse_iso
from procedures.kinds.iso._parameters import Iso9283Repeatability, IsoParameters, cube_path
from procedures.station import StationFile
from procedures.store import Reference, Sample, SessionConditions, as_pose


@dataclass
class IsoSession:
    """What one session of an ISO run remembers between steps: the last commanded TCP pose, and the
    direction the step being measured was approached from."""

    last_tcp: list[float] | None = None
    approach: dict[str, int | None] | None = None


class Iso9283RepeatabilityKind:
    """The transform pass (phase ``transform``), then the cycles (phase ``iso``).

    The first move of every session records the test conditions (robot identity, payload set on it,
    warm-up, operator); every pose records the direction it was approached from and, when the
    station has an interferometer, the air.
    """

    name = "iso9283_repeatability"
    parameters = IsoParameters
    file_model = Iso9283Repeatability
    result_shape = ResultShape.ISO_POSE
    iso_test_conditions = True
    measures_in_motion = False
    history_figures = ("rp_l", "rp_a", "rp_b", "rp_c", "ap_p")

    def plan(self, params: IsoParameters, station: StationFile) -> list[Step]:
        points = cube_path(params, station)
        setup = OprOnRobot()
        environment = params.record_environment and station.devices.interferometer is not None
        passes = ([("transform", 0)] if params.transform_step else []) + [("iso", c) for c in range(params.cycles)]
        steps: list[Step] = []
        for phase, cycle in passes:
            for label, point, tcp_pose in points:
                steps.append(Step(
                    index=len(steps), key=f"{phase}/c{cycle:03d}/{label}", phase=phase, setup=setup,
                    tcp_pose=tcp_pose, label=label,
                    meta={"cycle": cycle, "point": label, "position_in_m": point, "environment": environment},
                ))
        return steps

    def devices(self, params: IsoParameters) -> tuple[DeviceRole, ...]:
        return ("robot",)

    def applies_compensation(self, params: IsoParameters) -> bool:
        return params.apply_compensation

    def move(self, step: Step, params: IsoParameters, ctx: StepContext) -> None:
        record = ctx.session_state(SessionRecord)
        if record.conditions is None:
            record.start(self._conditions(params, ctx))
        state = ctx.session_state(IsoSession)
        reference = ctx.station.frames.reference_tcp_pose
        target = step.robot_target()
        previous = state.last_tcp
        if previous is None:
            previous = [float(v) for v in ctx.robot.tcp_pose()]
        state.approach = pose_directions(robot_pose_in_m(reference, previous), robot_pose_in_m(reference, target))
        ctx.move_robot(target)
        state.last_tcp = list(target)

    def _conditions(self, params: IsoParameters, ctx: StepContext) -> SessionConditions:
        """Identity, payload, warm-up and operator at the start of this session."""
        started = time.time()
        robot = robot_identity(ctx)
        payload = set_payload(ctx, params.payload_mass_kg, params.payload_cog_m)
        path = [tcp for _, _, tcp in cube_path(params, ctx.station)]
        return SessionConditions(started=started, robot=robot, payload=payload,
                                 warm_up=warm_up(ctx, params.warm_up, params.warm_up_s, path),
                                 operator=operator_of(params.operator))

    def measure(self, step: Step, params: IsoParameters, ctx: StepContext) -> Reading:
        ctx.settle()
        approach = ctx.session_state(IsoSession).approach
        environment = None
        if step.meta.get("environment"):
            environment = environment_record(read_environment(ctx, params, step.key))
        reference = Reference(robot_tcp_pose=as_pose(ctx.robot.tcp_pose()), approach=approach, environment=environment)
        expected = robot_pose_in_m(ctx.station.frames.reference_tcp_pose, step.robot_target())
        return Reading(pose=ctx.measure_pose(step, direction=approach, expected=dict(enumerate(expected))),
                       reference=reference, session=ctx.session_state(SessionRecord).take())

    def analyse(self, samples: Sequence[Sample], params: IsoParameters, ctx: AnalysisContext) -> Analysis:
        return Analysis(results=analyse_iso(samples, ctx, params))

    def title(self, parameters: Mapping[str, Any], results: Mapping[str, Any] | None) -> str:
        """"ISO 9283 pose repeatability and accuracy — N cycles": the fewest cycles measured at a point once the
        run has results, else the cycles it plans ("— N cycles planned"); never the procedure file's name,
        which may say 30 cycles of a 5-cycle run."""
        title = "ISO 9283 pose repeatability and accuracy"
        points = (results or {}).get("points") or {}
        counts = [int(p.get("n", 0)) for p in points.values() if isinstance(p, Mapping)]
        cycles = parameters.get("cycles")
        n = min(counts) if counts else int(cycles) if isinstance(cycles, (int, float)) else None
        if n is None:
            return title
        return title + f" — {n} cycle{'s' if n != 1 else ''}" + ("" if points else " planned")


KIND = Iso9283RepeatabilityKind()
