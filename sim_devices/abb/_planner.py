"""From RAPID motion commands to the arm core's motions: targets through the program's work object,
reachability checked before anything moves, speeds and zones as the IRC5 plans them.

- consecutive ``MoveL``/``MoveC`` run as one path (``sim_devices.arm.PathPlan``); a zone
  (``pzone_tcp`` mm) rounds the corner as a blend of that radius, reduced to half of either
  neighbouring segment as the controller reduces overlapping zones; a fine point ends the run;
- ``MoveJ``/``MoveAbsJ`` are synchronised joint moves taking as long as the TCP's chord at
  ``v_tcp`` (or the reorientation at ``v_ori``), capped by the axis speed limits;
- a single ``MoveL`` runs at ``v_tcp`` slowed to what ``v_ori`` allows for its reorientation (the
  move lasts as long as the slower of the two); a pure reorientation runs at ``v_ori``;
- the acceleration is the planner's (``path_acceleration``, ``joint_acceleration``).

Every point of a path is solved for the joints before it starts (outside the core's lock: the
controller cycle must not wait for it); a target out of reach or beyond an axis limit is RAPID
error 50050, a degenerate circle 50063.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from sim_devices._transforms import make_transform, matrix_to_rotvec, rotvec_to_matrix
from sim_devices.abb import _program as mp
from sim_devices.abb._config import ABBTwinConfig
from sim_devices.abb._kinematics import pose_from_abb, within_limits
from sim_devices.arm import IKFailed, Motion, Move, PathError, PathPlan, SerialArm

PATH_CHECK_SAMPLES = 24  # points per run at which a path's joints are solved before it starts


class RapidError(Exception):
    """A RAPID execution error: its event code, title and text."""

    def __init__(self, code: int, title: str, text: str) -> None:
        super().__init__(f"{code} {title}: {text}")
        self.code, self.title, self.text = code, title, text


def is_stop_point(command: mp.Command) -> bool:
    """A command without a zone, or with a fine point or a zero TCP zone: the arm stops there."""
    zone = command.params.get("zone")
    return zone is None or zone.finep or zone.pzone_tcp <= 0


class Planner:
    """Checked motion factories for the arm ``kin`` (see the module docstring)."""

    def __init__(self, kin: SerialArm, config: ABBTwinConfig) -> None:
        self.kin = kin
        self.config = config

    @staticmethod
    def _target(target: mp.RobTarget, frames: np.ndarray) -> np.ndarray:
        return frames @ pose_from_abb(target.pose.trans, target.pose.rot)

    def _solve(self, pose: np.ndarray, q_near: np.ndarray, tcp: np.ndarray) -> np.ndarray:
        try:
            q = self.kin.inverse(pose, q_near, tcp)
        except IKFailed:
            raise RapidError(50050, "Position outside reach", "The position (robtarget) is outside the robot's "
                             "working area") from None
        axis = within_limits(q)
        if axis is not None:
            raise RapidError(50050, "Position outside reach", f"axis {axis} would be outside its working range")
        return q

    def joint(self, command: mp.Command, q: np.ndarray, tcp: np.ndarray,
              frames: np.ndarray) -> Callable[[float, np.ndarray, np.ndarray], Motion]:
        """The checked MoveAbsJ/MoveJ from ``q``, as a motion factory for the core."""
        speed: mp.SpeedData = command.params["speed"]
        if command.name == "MoveAbsJ":
            target_q = np.radians(command.params["joints"][:6])
            axis = within_limits(target_q)
            if axis is not None:
                raise RapidError(50050, "Position outside reach", f"axis {axis} is outside its working range")
        else:
            target_q = self._solve(self._target(command.params["target"], frames), q, tcp)
        delta = np.abs(target_q - q)
        start, end = self.kin.forward(q, tcp), self.kin.forward(target_q, tcp)
        chord = float(np.linalg.norm(end[:3, 3] - start[:3, 3]))
        turn = float(np.linalg.norm(matrix_to_rotvec(end[:3, :3] @ start[:3, :3].T)))
        duration = max(chord / max(speed.v_tcp * 1e-3, 1e-9), turn / max(math.radians(speed.v_ori), 1e-9))
        biggest = float(np.max(delta))
        limits = np.asarray(self.config.joint_speed_limits)
        moving = delta > 1e-12
        cap = float(np.min(limits[moving] * biggest / delta[moving])) if np.any(moving) else float(np.min(limits))
        joint_speed = max(min(cap, biggest / duration) if duration > 0 else cap, 1e-6)
        return lambda t, q0, tcp0: Motion("joint", t, q0, tcp0, kinematics=self.kin, speed=joint_speed,
                                          accel=self.config.joint_acceleration, target_q=target_q)

    def path(self, group: list[mp.Command], q: np.ndarray, tcp: np.ndarray,
             frames: np.ndarray) -> Callable[[float, np.ndarray, np.ndarray], Motion]:
        """The checked MoveL/MoveC run from ``q`` (every point of it reachable), as a motion factory."""
        start = self.kin.forward(q, tcp)
        if len(group) == 1 and group[0].name in ("MoveL", "EGMMoveL"):
            return self._linear(group[0], q, tcp, start, frames)
        moves: list[Move] = []
        corners = [start[:3, 3]]
        for command in group:
            speed: mp.SpeedData = command.params["speed"]
            zone: mp.ZoneData = command.params["zone"]
            target = self._target(command.params["target"], frames)
            via = self._target(command.params["via"], frames) if "via" in command.params else None
            blend = 0.0 if is_stop_point(command) else zone.pzone_tcp * 1e-3
            moves.append(Move("circular" if via is not None else "linear", target, speed.v_tcp * 1e-3,
                              self.config.path_acceleration, blend, via))
            corners.append(target[:3, 3])
        for i in range(len(moves) - 1):  # the controller reduces a zone to half of either neighbour
            half = 0.5 * min(float(np.linalg.norm(corners[i + 1] - corners[i])),
                             float(np.linalg.norm(corners[i + 2] - corners[i + 1])))
            if moves[i].blend > half and moves[i].kind == moves[i + 1].kind == "linear":
                moves[i].blend = half
        try:
            plan = PathPlan(start, moves)
        except PathError as exc:
            code, title = (50063, "Circle uncertain") if any(m.kind == "circular" for m in moves) else \
                (50024, "Corner path failure")
            raise RapidError(code, title, str(exc)) from None
        q_check = q
        for index, run in enumerate(plan.runs):  # every point of the path must be reachable
            for s in np.linspace(0.0, run.length, PATH_CHECK_SAMPLES):
                q_check = self._solve(plan.pose(index, float(s)), q_check, tcp)
        return lambda t, q0, tcp0: Motion("path", t, q0, tcp0, kinematics=self.kin, plan=plan)

    def _linear(self, command: mp.Command, q: np.ndarray, tcp: np.ndarray, start: np.ndarray,
                frames: np.ndarray) -> Callable[[float, np.ndarray, np.ndarray], Motion]:
        speed: mp.SpeedData = command.params["speed"]
        target = self._target(command.params["target"], frames)
        self._solve(target, q, tcp)
        translation = float(np.linalg.norm(target[:3, 3] - start[:3, 3]))
        rotation = float(np.linalg.norm(matrix_to_rotvec(target[:3, :3] @ start[:3, :3].T)))
        v_ori = math.radians(max(speed.v_ori, 1e-9))
        if translation > 1e-7:
            v = speed.v_tcp * 1e-3
            if rotation > 0 and rotation / v_ori > translation / v:
                v = translation * v_ori / rotation  # the reorientation takes longer: the whole move slows
        else:
            v = v_ori
        q_check = q
        for u in np.linspace(0.0, 1.0, PATH_CHECK_SAMPLES)[1:-1]:  # every point of the line must be reachable
            rot = _slerp(start[:3, :3], target[:3, :3], u)
            q_check = self._solve(make_transform(rot, start[:3, 3] + u * (target[:3, 3] - start[:3, 3])), q_check, tcp)
        accel = self.config.path_acceleration
        return lambda t, q0, tcp0: Motion("linear", t, q0, tcp0, kinematics=self.kin, speed=v, accel=accel,
                                          target_pose=target)


def _slerp(r0: np.ndarray, r1: np.ndarray, u: float) -> np.ndarray:
    return rotvec_to_matrix(u * matrix_to_rotvec(r1 @ r0.T)) @ r0
