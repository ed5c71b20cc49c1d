"""The dry run: everything that can be checked before the first motion, over the remaining steps.

Targets inside the envelope, speed and acceleration within its caps, every cross on its screen
(the core's exact forward model), and every device the kind needs reachable and healthy.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence

import numpy as np

from drivers import MotionRefused
from procedures._geometry import matrix_to_euler, tcp_in_m
from procedures._science import Science
from procedures._station import StationRuntime
from procedures._step_context import SCREENS, robot_speed
from procedures.kinds import DeviceRole, MotionParameters, Step

# The order devices are opened and reported in: the robot first, the references last.
_ROLE_ORDER = ("robot", *(f"camera:{s}" for s in SCREENS), "rotary_table", "interferometer")


def _robot_health(station: StationRuntime) -> list[str]:
    state = station.robot.state()
    if state.emergency_stop:
        return ["robot: emergency stop engaged"]
    if state.protective_stop:
        return ["robot: in protective stop"]
    if not state.program_running:
        return ["robot: control program not running"]
    return []


def _table_health(station: StationRuntime) -> list[str]:
    state = station.table.state()
    return [f"rotary table: fault {state.fault}"] if state.fault else []


# The interferometer has no check here: its beam means something only once aligned, and the
# first reading says whether it does.
_HEALTH: dict[str, Callable[[StationRuntime], list[str]]] = {"robot": _robot_health, "rotary_table": _table_health}


def plan_problems(todo: Sequence[Step], devices: Collection[DeviceRole], station: StationRuntime, science: Science,
                  params: MotionParameters) -> list[str]:
    """Every problem of the steps ``todo`` on ``station`` (empty: the run may start). Opens the devices."""
    problems: list[str] = []
    envelope = station.envelope
    robot_steps = [(step, step.robot_target()) for step in todo if step.tcp_pose is not None]
    if robot_steps:
        try:
            envelope.check_speed(*robot_speed(envelope, params))
        except MotionRefused as exc:
            problems.append(f"speed: {exc.cause}")
    unseen: dict[str, Step] = {}  # each visibility problem once, at the first step that has it
    for step, tcp_pose in robot_steps:
        try:
            envelope.check_pose(np.asarray(tcp_pose))
        except MotionRefused as exc:
            problems.append(f"step {step.key}: {exc.cause}")
        opr = matrix_to_euler(tcp_in_m(station.reference_tcp_pose, tcp_pose))
        for problem in science.visibility_problems(opr):
            unseen.setdefault(problem, step)
    problems += [f"step {step.key}: {problem}" for problem, step in unseen.items()]
    wanted = {f"camera:{s}" for s in SCREENS} | set(devices)
    for role in (r for r in _ROLE_ORDER if r in wanted):
        try:
            station.device(role)
            problems += _HEALTH.get(role, lambda _: [])(station)
        except Exception as exc:
            problems.append(f"{role}: not reachable: {exc}")
    return problems
