"""Approach direction (issue 14): from which side a pose component was reached.

A calibration may visit each point from below only (``approach: one``, +1) or from below and from
above (``both``): each pass over a line's points is made in one direction, and a point is approached
from the wanted side by first moving ``overshoot`` beyond it on the other side whenever the robot
(or the table) does not already come from that side. The direction of every calibration sample is
therefore known from the plan (``meta["approach"]``), including after a resume or a re-established
datum, which approach again.

An ISO cycle approaches its points as the cycle goes; each component's direction is the sign of
(commanded − previous commanded) in M (the robot's actual pose before the first move of a
session), None where the component does not change.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from instrument import COMPONENTS
from procedures.kinds._protocol import Step, StepContext
from procedures.station import matrix_to_euler, tcp_in_m, translated_in_frame

Approach = Literal["one", "both"]
MOVED_M = 1e-6  # a component that moved less than this (m) is not approached from either side
MOVED_RAD = 1e-6
_SLACK = 1e-9


@dataclass
class WhereItStands:
    """Where this session last left the robot on a calibration line and the table on an axis (the approach
    helpers' memory for one session: a resumed run knows neither, and approaches afresh)."""

    line: tuple[tuple[str, int], float] | None = None  # ((axis, group), position along the axis, m)
    table: tuple[str, float] | None = None  # (axis, angle, rad)


def directions_of(approach: Approach) -> tuple[int, ...]:
    """The passes a calibration makes over its points: +1 (from below), then −1 (from above)."""
    return (1,) if approach == "one" else (1, -1)


def pose_directions(previous_in_m: Sequence[float] | None, target_in_m: Sequence[float]) -> dict[str, int | None]:
    """Per component, +1 when ``target`` lies above ``previous`` (approached from below), −1 below,
    None when it did not move (or ``previous`` is unknown)."""
    if previous_in_m is None:
        return dict.fromkeys(COMPONENTS)
    delta = np.asarray(target_in_m, dtype=float) - np.asarray(previous_in_m, dtype=float)
    delta[3:] = (delta[3:] + np.pi) % (2 * np.pi) - np.pi
    out: dict[str, int | None] = {}
    for k, component in enumerate(COMPONENTS):
        moved = MOVED_M if k < 3 else MOVED_RAD
        out[component] = None if abs(delta[k]) < moved else int(np.sign(delta[k]))
    return out


def robot_pose_in_m(reference_tcp_pose: Sequence[float], tcp_pose: Sequence[float]) -> list[float]:
    """A UR TCP pose (base frame) as the OPR's pose in nominal M, ``[x, y, z, a, b, c]``."""
    return [float(v) for v in matrix_to_euler(tcp_in_m(reference_tcp_pose, tcp_pose))]


def approach_on_line(ctx: StepContext, step: Step, axis_index: int, overshoot_m: float) -> None:
    """Move the robot to a calibration step's target, reaching it from ``step.meta["approach"]``'s side.

    The last position on the step's line (its axis and group) this session is kept in its
    ``WhereItStands``; a pre-position ``overshoot_m`` short of the target (along the axis, on the
    approach side) is inserted unless the robot already comes from at least that far on that side.
    """
    direction = step.meta.get("approach")
    target = step.robot_target()
    line = (step.meta["axis"], step.meta["group"])
    value = float(step.meta["nominal"])
    memory = ctx.session_state(WhereItStands)
    last = memory.line
    if direction is not None and not (last is not None and last[0] == line
                                      and (value - last[1]) * direction >= overshoot_m - _SLACK):
        along = np.zeros(3)
        along[axis_index] = -direction * overshoot_m
        ctx.move_robot(translated_in_frame(target, along).tolist())
    ctx.move_robot(target)
    memory.line = (line, value)


def note_line_position(ctx: StepContext, step: Step, value: float) -> None:
    """Record that the robot stands at ``value`` on the step's line (after a move made elsewhere)."""
    ctx.session_state(WhereItStands).line = ((step.meta["axis"], step.meta["group"]), float(value))


def approach_table(ctx: StepContext, step: Step, speed: float, overshoot_rad: float) -> None:
    """Turn the table to a step's angle from ``step.meta["approach"]``'s side (see ``approach_on_line``)."""
    direction = step.meta.get("approach")
    angle = step.table_target()
    axis = step.meta["axis"]
    memory = ctx.session_state(WhereItStands)
    last = memory.table
    if direction is not None and not (last is not None and last[0] == axis
                                      and (angle - last[1]) * direction >= overshoot_rad - _SLACK):
        ctx.turn_table(angle - direction * overshoot_rad, speed=speed)
    ctx.turn_table(angle, speed=speed)
    memory.table = (axis, angle)
