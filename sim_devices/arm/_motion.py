"""Trapezoidal motions in simulated time: ``movel`` (Cartesian line + slerp), ``movej`` (synchronised
joint interpolation) and paths (``movel`` waypoints with blends and ``movec`` arcs, ``_path``), with a
deceleration stop that can cut any motion short.

A motion is a path ``x(s)``, ``s ∈ [0, L]``, driven by a 1-D velocity profile ``s(t)``. ``L`` is the
TCP travel in metres for ``movel`` (or the rotation angle in radians when the TCP only turns, as a UR
controller does) and the largest joint travel in radians for ``movej``; speeds and accelerations are
in the same units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim_devices._transforms import make_transform, matrix_to_rotvec, rotvec_to_matrix
from sim_devices.arm._dynamics import rotvec_to_matrix_batch
from sim_devices.arm._kinematics import SerialArm
from sim_devices.arm._path import PathPlan


@dataclass
class Profile:
    """Trapezoidal (or triangular) profile from rest to rest, or a pure deceleration from ``v0``."""

    t0: float
    s0: float
    length: float  # distance still to travel from s0
    v0: float
    v_peak: float
    accel: float  # acceleration of the ramp up (unused when decelerating from v0)
    decel: float
    t_acc: float
    t_flat: float
    t_dec: float

    @classmethod
    def rest_to_rest(cls, t0: float, length: float, speed: float, accel: float) -> Profile:
        length = max(length, 0.0)
        speed, accel = max(speed, 1e-9), max(accel, 1e-9)
        if length * accel < speed * speed:  # triangular: never reaches the speed
            v_peak = math.sqrt(length * accel)
            t_acc = v_peak / accel
            return cls(t0, 0.0, length, 0.0, v_peak, accel, accel, t_acc, 0.0, t_acc)
        t_acc = speed / accel
        t_flat = (length - speed * t_acc) / speed
        return cls(t0, 0.0, length, 0.0, speed, accel, accel, t_acc, t_flat, t_acc)

    @classmethod
    def stopping(cls, t0: float, s0: float, v0: float, decel: float) -> Profile:
        decel = max(decel, 1e-9)
        t_dec = max(v0, 0.0) / decel
        return cls(t0, s0, 0.5 * max(v0, 0.0) * t_dec, v0, v0, decel, decel, 0.0, 0.0, t_dec)

    @property
    def t_end(self) -> float:
        return self.t0 + self.t_acc + self.t_flat + self.t_dec

    def at(self, t: float) -> tuple[float, float]:
        """Path position and speed at simulated time ``t``."""
        tau = min(max(t - self.t0, 0.0), self.t_acc + self.t_flat + self.t_dec)
        if tau < self.t_acc:
            return self.s0 + 0.5 * self.accel * tau * tau, self.accel * tau
        s = self.s0 + 0.5 * self.accel * self.t_acc**2 if self.t_acc else self.s0
        tau -= self.t_acc
        if tau < self.t_flat:
            return s + self.v_peak * tau, self.v_peak
        s += self.v_peak * self.t_flat
        tau -= self.t_flat
        return s + self.v_peak * tau - 0.5 * self.decel * tau * tau, max(self.v_peak - self.decel * tau, 0.0)


class Motion:
    """A running move of the arm ``kinematics``. ``sample(t)`` gives the commanded joints and TCP pose
    at simulated time ``t``; ``pose_at(t)`` the commanded TCP pose alone (no inverse kinematics)."""

    def __init__(self, kind: str, t0: float, q_start: np.ndarray, tcp_offset: np.ndarray, *, kinematics: SerialArm,
                 speed: float = 0.0, accel: float = 0.0, target_q: np.ndarray | None = None,
                 target_pose: np.ndarray | None = None, plan: PathPlan | None = None) -> None:
        self.kind = kind  # "linear", "joint" or "path"
        self.kin = kin = kinematics
        self.tcp_offset = np.asarray(tcp_offset, dtype=float).copy()
        self.q_start = np.asarray(q_start, dtype=float).copy()
        self.start_pose = kin.forward(self.q_start, self.tcp_offset)
        self.stopped = False
        self._q_last = self.q_start.copy()
        self.plan = plan
        self.profiles: list[Profile] = []
        if kind == "path":
            assert plan is not None
            self.target_pose = plan.end_pose.copy()
            self.target_q = kin.inverse(self.target_pose, self.q_start, self.tcp_offset)
            self.length = plan.length
            start = t0
            for run in plan.runs:
                profile = Profile.rest_to_rest(start, run.length, run.speed, run.acceleration)
                self.profiles.append(profile)
                start = profile.t_end
            self._offsets = np.concatenate([[0.0], np.cumsum([run.length for run in plan.runs])])
            self.profile = self.profiles[-1]
            return
        if kind == "joint":
            self.target_q = np.asarray(target_q, dtype=float).copy()
            self.target_pose = kin.forward(self.target_q, self.tcp_offset)
            self.length = float(np.max(np.abs(self.target_q - self.q_start)))
        else:
            self.target_pose = np.asarray(target_pose, dtype=float).copy()
            # Reachability is checked before the move starts; the end joints keep the start branch.
            self.target_q = kin.inverse(self.target_pose, self.q_start, self.tcp_offset)
            self._dp = self.target_pose[:3, 3] - self.start_pose[:3, 3]
            self._drot = matrix_to_rotvec(self.target_pose[:3, :3] @ self.start_pose[:3, :3].T)
            translation, rotation = float(np.linalg.norm(self._dp)), float(np.linalg.norm(self._drot))
            self.length = translation if translation > 1e-7 else rotation
        self.profile = Profile.rest_to_rest(t0, self.length, speed, accel)

    @property
    def t_end(self) -> float:
        return self.profile.t_end

    def _path_state(self, t: float) -> tuple[int, float, float]:
        """(run, arc length in it, path speed) at ``t`` for a path."""
        for index, profile in enumerate(self.profiles):
            if t < profile.t_end or index == len(self.profiles) - 1:
                s, v = profile.at(t)
                return index, s, v
        raise AssertionError("unreachable")

    def fraction(self, t: float) -> float:
        if self.kind == "path":
            run, s, _ = self._path_state(t)
            return 1.0 if self.length <= 0 else min((self._offsets[run] + s) / self.length, 1.0)
        s, _ = self.profile.at(t)
        return 1.0 if self.length <= 0 else min(s / self.length, 1.0)

    def waypoints_passed(self, t: float) -> int:
        """How many of a path's waypoints the tool has passed at ``t`` (0 for other motions)."""
        if self.kind != "path":
            return 0
        assert self.plan is not None
        run, s, _ = self._path_state(t)
        earlier = sum(len(r.waypoint_s) - 1 for r in self.plan.runs[:run])
        return earlier + sum(1 for w in self.plan.runs[run].waypoint_s[1:] if w <= s)

    def time_at_fraction(self, fraction: float) -> float:
        """Simulated time at which the path reaches ``fraction`` (bisection on the monotonic profile)."""
        lo, hi = (self.profiles[0] if self.profiles else self.profile).t0, self.profile.t_end
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            if self.fraction(mid) < fraction:
                lo = mid
            else:
                hi = mid
        return hi

    def speed(self, t: float) -> float:
        if self.kind == "path":
            return self._path_state(t)[2]
        return self.profile.at(t)[1]

    def stop(self, t: float, decel: float) -> None:
        """Cut the motion short: decelerate from the current path speed at ``decel``."""
        if self.kind == "path":
            run, s, v = self._path_state(t)
            self.profiles = self.profiles[:run] + [Profile.stopping(t, s, v, decel)]
            self.profile = self.profiles[-1]
            self.stopped = True
            return
        s, v = self.profile.at(t)
        self.profile = Profile.stopping(t, s, v, decel)
        self.stopped = True

    def pose_at(self, t: float) -> np.ndarray:
        """The commanded TCP pose (4×4) at ``t``, without solving for the joints."""
        if self.kind == "path":
            assert self.plan is not None
            run, s, _ = self._path_state(t)
            return self.plan.pose(run, s)
        u = self.fraction(t)
        if self.kind == "joint":
            return self.kin.forward(self.q_start + u * (self.target_q - self.q_start), self.tcp_offset)
        if u >= 1.0:
            return self.target_pose.copy()
        rotation = rotvec_to_matrix(u * self._drot) @ self.start_pose[:3, :3]
        return make_transform(rotation, self.start_pose[:3, 3] + u * self._dp)

    def poses_at(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The commanded TCP poses (n, 4, 4) and path fractions (n,) at ``times``: ``pose_at`` and
        ``fraction`` for a batch (the truth grid's samples of one controller cycle), a linear move's
        poses in one vectorised step."""
        fractions = np.array([self.fraction(t) for t in times])
        if self.kind != "linear":
            return np.array([self.pose_at(t) for t in times]), fractions
        poses = np.repeat(self.target_pose[None], len(fractions), axis=0)  # a finished row: the target exactly
        moving = fractions < 1.0
        if moving.any():
            u = fractions[moving]
            poses[moving, :3, :3] = rotvec_to_matrix_batch(u[:, None] * self._drot) @ self.start_pose[:3, :3]
            poses[moving, :3, 3] = self.start_pose[:3, 3] + u[:, None] * self._dp
        return poses, fractions

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(joints, TCP pose 4×4) commanded at ``t``."""
        u = self.fraction(t)
        if self.kind == "joint":
            q = self.q_start + u * (self.target_q - self.q_start)
            return q, self.kin.forward(q, self.tcp_offset)
        if self.kind == "path":
            pose = self.pose_at(t)
            if u >= 1.0 and not self.stopped:
                self._q_last = self.target_q.copy()
                return self._q_last, self.target_pose.copy()
            self._q_last = self.kin.inverse(pose, self._q_last, self.tcp_offset, tolerance=1e-11)
            return self._q_last, pose
        if u >= 1.0:
            self._q_last = self.target_q.copy()
            return self._q_last, self.target_pose.copy()
        rotation = rotvec_to_matrix(u * self._drot) @ self.start_pose[:3, :3]
        pose = make_transform(rotation, self.start_pose[:3, 3] + u * self._dp)
        self._q_last = self.kin.inverse(pose, self._q_last, self.tcp_offset, tolerance=1e-11)
        return self._q_last, pose
