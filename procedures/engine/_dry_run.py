"""The dry run: everything that can be checked before the first motion, over the remaining steps.

Targets inside the envelope, speed and acceleration within its caps, every cross on its screen
(the core's exact forward model), the calibration records in force readable, and every device the
kind needs reachable and healthy. ``offline_problems`` is the part that needs no device (what
``instrument validate STATION PROCEDURE`` runs); ``plan_problems`` adds the devices.

A problem that repeats over many steps is reported once, at its first step, with the count of the
others (``collapse``): "step disp/x/g0/r0/p03: target ... outside the envelope (… and 106 more points)".
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass

import numpy as np

from drivers import MotionRefused
from drivers.robot import MotionEnvelope
from procedures.engine._step_context import SCREENS, robot_speed
from procedures.kinds import DeviceRole, MotionParameters, Step
from procedures.station import InputRefused, Science, StationRuntime, matrix_to_euler, tcp_in_m

# The order devices are opened and reported in: the robot first, the references last.
_ROLE_ORDER = ("robot", *(f"camera:{s}" for s in SCREENS), "rotary_table", "interferometer")


@dataclass(frozen=True)
class Problem:
    """One thing that would stop the run.

    ``kind`` names what is wrong regardless of where (problems of one kind are collapsed),
    ``text`` is the whole line for the first one.
    """

    kind: str
    text: str


def collapse(problems: Sequence[Problem]) -> list[str]:
    """One line per kind of problem, in the order first seen; repeats counted, not listed."""
    first: dict[str, str] = {}
    count: dict[str, int] = {}
    for problem in problems:
        first.setdefault(problem.kind, problem.text)
        count[problem.kind] = count.get(problem.kind, 0) + 1
    return [text + (f" (… and {count[kind] - 1} more points)" if count[kind] > 1 else "")
            for kind, text in first.items()]


def offline_problems(todo: Sequence[Step], envelope: MotionEnvelope, reference_tcp_pose: np.ndarray,
                     science: Science, params: MotionParameters) -> list[Problem]:
    """The problems of the steps ``todo`` that need no device: envelope, speed, crosses on screens.
    ``science`` must be configured with the station's geometry."""
    problems: list[Problem] = []
    robot_steps = [(step, step.robot_target()) for step in todo if step.tcp_pose is not None]
    if robot_steps:
        try:
            envelope.check_speed(*robot_speed(envelope, params))
        except MotionRefused as exc:
            problems.append(Problem("speed", f"speed: {exc.cause}"))
    judged: dict[tuple[float, ...], list[Problem]] = {}  # repeats and cycles revisit the same poses
    for step, tcp_pose in robot_steps:
        key = tuple(float(v) for v in tcp_pose)
        if key not in judged:
            judged[key] = []
            try:
                envelope.check_pose(np.asarray(tcp_pose))
            except MotionRefused as exc:
                judged[key].append(Problem("envelope", exc.cause))
            opr = matrix_to_euler(tcp_in_m(reference_tcp_pose, tcp_pose))
            judged[key] += [Problem("visibility", problem) for problem in science.visibility_problems(opr)]
        problems += [Problem(p.kind, f"step {step.key}: {p.text}") for p in judged[key]]
        for via in step.via:  # an approach's pre-position: only moved through, so only the envelope matters
            try:
                envelope.check_pose(np.asarray(via))
            except MotionRefused as exc:
                problems.append(Problem("envelope", f"step {step.key} (approach pre-position): {exc.cause}"))
    return problems


def record_problems(paths: Sequence[str], science: Science) -> list[Problem]:
    """Calibration record files that do not exist, are no files, or do not parse as records."""
    problems: list[Problem] = []
    for path in paths:
        try:
            science.load_compensator(path)
        except InputRefused as exc:
            problems.append(Problem(f"record {path}", f"calibration.record: {exc}"))
        except IsADirectoryError:
            problems.append(Problem(f"record {path}", f"calibration.record: {path} is a folder, not a record file"))
        except OSError as exc:
            problems.append(Problem(f"record {path}", f"calibration.record: cannot read {path}: "
                                                      f"{exc.strerror or exc}"))
        except (ValueError, KeyError, TypeError) as exc:
            why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            problems.append(Problem(f"record {path}", f"calibration.record: {path} is not a calibration record: {why}"))
    return problems


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
                  params: MotionParameters) -> list[Problem]:
    """Every problem of the steps ``todo`` on ``station`` (empty: the run may start). Opens the devices.

    The calibration records are not checked here: the engine has loaded them already.
    """
    problems = offline_problems(todo, station.envelope, station.reference_tcp_pose, science, params)
    wanted = {f"camera:{s}" for s in SCREENS} | set(devices)
    for role in (r for r in _ROLE_ORDER if r in wanted):
        try:
            station.device(role)
            problems += [Problem(role, text) for text in _HEALTH.get(role, lambda _: [])(station)]
        except Exception as exc:
            problems.append(Problem(role, f"{role}: not reachable: {exc}"))
    return problems
