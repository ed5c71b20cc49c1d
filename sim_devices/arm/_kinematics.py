"""Six-axis serial arms for the robot twins: standard Denavit–Hartenberg forward kinematics and a
numerical inverse.

``SerialArm`` holds one arm's DH table (``d``, ``a``, ``alpha`` and a joint-angle offset ``theta0``
that maps the controller's joint zero onto the DH zero). The forward kinematics gives the flange
(tool0) pose in the base frame; a TCP offset ``T_F_TCP`` (UR pose ``[x, y, z, rx, ry, rz]``) is
composed on the right. The inverse is a damped Newton iteration started from ``qnear`` (the
current joints by default), so it returns the solution in the same configuration branch, which is
what a controller does when it solves a Cartesian target near its current joints.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sim_devices._transforms import invert, matrix_to_pose6, matrix_to_rotvec, pose6_to_matrix


class IKFailed(ValueError):
    """No joint solution reaches the pose (out of reach or singular)."""


@dataclass(frozen=True)
class SerialArm:
    """A six-axis arm by its standard DH parameters.

    Parameters
    ----------
    name : str
        What the arm is (for messages), e.g. ``"UR5e"``.
    d, a, alpha : six floats each (sequences or arrays)
        DH link offsets and lengths (m) and twists (rad).
    home_seed : six floats
        A comfortable configuration to start the inverse from when nothing better is known.
    theta0 : six floats
        Added to each controller joint angle before the DH transform (zeros: the controller's zero
        is the DH zero, as on a UR).
    """

    name: str
    d: Any
    a: Any
    alpha: Any
    home_seed: Any
    theta0: Any = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for key in ("d", "a", "alpha", "home_seed", "theta0"):
            object.__setattr__(self, key, np.asarray(getattr(self, key), dtype=float).reshape(6))
        self._cache["ca"] = np.cos(self.alpha)
        self._cache["sa"] = np.sin(self.alpha)
        self._cache["offset"] = bool(np.any(self.theta0))

    def _dh_all(self, q) -> np.ndarray:
        """The six DH link transforms at once (6, 4, 4): one array expression instead of six small ones."""
        q = np.asarray(q, dtype=float)
        if self._cache["offset"]:
            q = q + self.theta0
        ca, sa = self._cache["ca"], self._cache["sa"]
        ct, st = np.cos(q), np.sin(q)
        links = np.zeros((6, 4, 4))
        links[:, 0, 0], links[:, 0, 1], links[:, 0, 2], links[:, 0, 3] = ct, -st * ca, st * sa, self.a * ct
        links[:, 1, 0], links[:, 1, 1], links[:, 1, 2], links[:, 1, 3] = st, ct * ca, -ct * sa, self.a * st
        links[:, 2, 1], links[:, 2, 2], links[:, 2, 3] = sa, ca, self.d
        links[:, 3, 3] = 1.0
        return links

    def joint_frames(self, q) -> list[np.ndarray]:
        """Base-frame transforms of frames 0..6 (0 = base, 6 = flange)."""
        frames = [np.eye(4)]
        t = frames[0]
        for link in self._dh_all(q):
            t = t @ link
            frames.append(t)
        return frames

    def forward(self, q, tcp_offset=None) -> np.ndarray:
        """4×4 TCP pose in the base frame for joints ``q`` and TCP offset (UR pose, flange frame)."""
        flange = self.joint_frames(q)[-1]
        if tcp_offset is None:
            return flange
        return flange @ pose6_to_matrix(tcp_offset)

    def forward_pose(self, q, tcp_offset=None) -> np.ndarray:
        """Like ``forward`` but returns a UR pose ``[x, y, z, rx, ry, rz]``."""
        return matrix_to_pose6(self.forward(q, tcp_offset))

    def _jacobian(self, q, tcp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Geometric Jacobian (6×6, [v; ω]) at the TCP, and the TCP transform."""
        frames = self.joint_frames(q)
        end = frames[-1] @ tcp
        stacked = np.array(frames[:6])
        z = stacked[:, :3, 2]  # joint axes (6, 3)
        r = end[:3, 3] - stacked[:, :3, 3]  # joint origin → TCP (6, 3)
        jac = np.empty((6, 6))
        # z × r, written out: np.cross costs more than the rest of the Jacobian for 3-vectors.
        jac[0] = z[:, 1] * r[:, 2] - z[:, 2] * r[:, 1]
        jac[1] = z[:, 2] * r[:, 0] - z[:, 0] * r[:, 2]
        jac[2] = z[:, 0] * r[:, 1] - z[:, 1] * r[:, 0]
        jac[3:] = z.T
        return jac, end

    def inverse(self, target, qnear, tcp_offset=None, *, tolerance: float = 1e-10,
                max_iterations: int = 100) -> np.ndarray:
        """Joints reaching the TCP pose ``target`` (4×4 or UR pose), started from ``qnear``.

        Raises ``IKFailed`` when the iteration does not converge (pose out of reach).
        """
        target = np.asarray(target, dtype=float)
        target = pose6_to_matrix(target) if target.shape == (6,) else target
        tcp = np.eye(4) if tcp_offset is None else pose6_to_matrix(tcp_offset)
        q = np.array(qnear, dtype=float).reshape(6)
        damping = 1e-6
        for _ in range(max_iterations):
            jac, end = self._jacobian(q, tcp)
            dp = target[:3, 3] - end[:3, 3]
            dr = matrix_to_rotvec(target[:3, :3] @ end[:3, :3].T)
            err = np.concatenate([dp, dr])
            if np.linalg.norm(err) < tolerance:
                return _wrap_near(q, qnear)
            jjt = jac @ jac.T + damping * np.eye(6)
            step = jac.T @ np.linalg.solve(jjt, err)
            norm = np.linalg.norm(step)
            if norm > 0.5:  # keep steps small so the iteration stays on the seed's branch
                step *= 0.5 / norm
            q = q + step
        raise IKFailed(f"inverse kinematics did not converge for pose {matrix_to_pose6(target).round(6).tolist()}")

    @staticmethod
    def flange_from_tcp(tcp_pose: np.ndarray, tcp_offset) -> np.ndarray:
        """Flange pose (4×4) from a TCP pose (4×4) and the TCP offset (UR pose)."""
        return tcp_pose @ invert(pose6_to_matrix(tcp_offset))


def _wrap_near(q: np.ndarray, qnear) -> np.ndarray:
    """Shift each joint by multiples of 2π to lie nearest ``qnear``."""
    qnear = np.asarray(qnear, dtype=float)
    return qnear + (q - qnear + np.pi) % (2 * np.pi) - np.pi
