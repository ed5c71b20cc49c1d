"""Rotations and the ``Pose`` dataclass (paper convention R = Rz(γ)·Ry(θ)·Rx(α), fixed axes).

A ``Pose`` maps coordinates in the moving frame to the reference frame: p_ref = R·p + t, so as a
4×4 matrix it is ``T_ref_moving``. ISO 9283's (a, b, c) are (α, θ, γ).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

_EYE = np.eye(3)


def rot_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_to_matrix(alpha: float, theta: float, gamma: float) -> np.ndarray:
    """R = Rz(γ)·Ry(θ)·Rx(α): rotate about fixed X by α, then fixed Y by θ, then fixed Z by γ.

    Written out (method.md eq. 4) rather than as three matrix products: this runs once per solve.
    """
    ca, sa, ct, st = math.cos(alpha), math.sin(alpha), math.cos(theta), math.sin(theta)
    cg, sg = math.cos(gamma), math.sin(gamma)
    return np.array(
        [
            [cg * ct, cg * st * sa - sg * ca, cg * st * ca + sg * sa],
            [sg * ct, sg * st * sa + cg * ca, sg * st * ca - cg * sa],
            [-st, ct * sa, ct * ca],
        ]
    )


def euler_to_matrix_with_derivatives(alpha: float, theta: float, gamma: float):
    """R and its partial derivatives ∂R/∂α, ∂R/∂θ, ∂R/∂γ (for the solver's analytic Jacobian)."""
    ca, sa, ct, st, cg, sg = np.cos(alpha), np.sin(alpha), np.cos(theta), np.sin(theta), np.cos(gamma), np.sin(gamma)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]])
    ry = np.array([[ct, 0.0, st], [0.0, 1.0, 0.0], [-st, 0.0, ct]])
    rz = np.array([[cg, -sg, 0.0], [sg, cg, 0.0], [0.0, 0.0, 1.0]])
    drx = np.array([[0.0, 0.0, 0.0], [0.0, -sa, -ca], [0.0, ca, -sa]])
    dry = np.array([[-st, 0.0, ct], [0.0, 0.0, 0.0], [-ct, 0.0, -st]])
    drz = np.array([[-sg, -cg, 0.0], [cg, -sg, 0.0], [0.0, 0.0, 0.0]])
    rzy = rz @ ry
    return rzy @ rx, rzy @ drx, rz @ dry @ rx, drz @ ry @ rx


def matrix_to_euler(rotation) -> np.ndarray:
    """(α, θ, γ) of R = Rz(γ)·Ry(θ)·Rx(α), θ in [−π/2, π/2] (singular at |θ| = π/2)."""
    r = np.asarray(rotation, dtype=float)
    theta = np.arctan2(-r[2, 0], np.hypot(r[0, 0], r[1, 0]))
    alpha = np.arctan2(r[2, 1], r[2, 2])
    gamma = np.arctan2(r[1, 0], r[0, 0])
    return np.array([alpha, theta, gamma])


def _check_rotation(rotation, name: str = "rotation") -> np.ndarray:
    r = np.asarray(rotation, dtype=float)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise ValueError(f"{name}: expected a finite 3×3 rotation matrix, got shape {r.shape}")
    # Plain max/det rather than np.allclose: this runs on every Pose and allclose costs ~30 µs.
    if float(np.abs(r @ r.T - _EYE).max()) > 1e-8 or np.linalg.det(r) < 0:
        raise ValueError(f"{name}: not a proper rotation (orthonormal, det +1): {r.tolist()}")
    return r


@dataclass(frozen=True)
class Pose:
    """A rigid pose: translation (3,) m and rotation (3×3); p_ref = rotation·p + translation.

    Build with ``Pose(t, R)``, ``Pose.from_euler(t, (α, θ, γ))``, ``Pose.from_matrix(T)``,
    ``Pose.from_iso([x, y, z, a, b, c])`` or ``Pose.from_rotvec_pose([x, y, z, rx, ry, rz])``
    (the robot's / station file's convention).
    """

    translation: np.ndarray
    rotation: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.translation, dtype=float).reshape(-1)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise ValueError(f"Pose.translation: expected 3 finite numbers, got {self.translation!r}")
        r = _check_rotation(self.rotation, "Pose.rotation")
        t.setflags(write=False)
        r = r.copy()
        r.setflags(write=False)
        object.__setattr__(self, "translation", t)
        object.__setattr__(self, "rotation", r)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def identity(cls) -> Pose:
        return cls(np.zeros(3), np.eye(3))

    @classmethod
    def from_euler(cls, translation, euler) -> Pose:
        alpha, theta, gamma = (float(a) for a in euler)
        return cls(translation, euler_to_matrix(alpha, theta, gamma))

    @classmethod
    def from_iso(cls, vector) -> Pose:
        """From ISO 9283's [x, y, z, a, b, c] (m, rad), (a, b, c) = (α, θ, γ)."""
        v = np.asarray(vector, dtype=float).reshape(-1)
        if v.shape != (6,):
            raise ValueError(f"Pose.from_iso: expected [x, y, z, a, b, c], got {vector!r}")
        return cls.from_euler(v[:3], v[3:])

    @classmethod
    def from_rotvec_pose(cls, vector) -> Pose:
        """From [x, y, z, rx, ry, rz] with a rotation vector (UR / station file convention)."""
        from scipy.spatial.transform import Rotation
        v = np.asarray(vector, dtype=float).reshape(-1)
        if v.shape != (6,) or not np.all(np.isfinite(v)):
            raise ValueError(f"Pose.from_rotvec_pose: expected 6 finite numbers, got {vector!r}")
        return cls(v[:3], Rotation.from_rotvec(v[3:]).as_matrix())

    @classmethod
    def from_matrix(cls, matrix) -> Pose:
        m = np.asarray(matrix, dtype=float)
        if m.shape != (4, 4) or not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0]):
            raise ValueError(f"Pose.from_matrix: expected a 4×4 homogeneous transform, got shape {m.shape}")
        return cls(m[:3, 3], m[:3, :3])

    # ------------------------------------------------------------------ views
    @property
    def euler(self) -> np.ndarray:
        """(α, θ, γ), rad, with R = Rz(γ)·Ry(θ)·Rx(α)."""
        return matrix_to_euler(self.rotation)

    @property
    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.translation
        return m

    def as_iso(self) -> np.ndarray:
        """[x, y, z, a, b, c] (m, rad) for ``instrument.iso9283``."""
        return np.concatenate([self.translation, self.euler])

    def as_rotvec_pose(self) -> np.ndarray:
        from scipy.spatial.transform import Rotation
        return np.concatenate([self.translation, Rotation.from_matrix(self.rotation).as_rotvec()])

    # ------------------------------------------------------------------ algebra
    def compose(self, other: Pose) -> Pose:
        """self ∘ other: if self is T_a_b and other T_b_c, the result is T_a_c."""
        return Pose(self.rotation @ other.translation + self.translation, self.rotation @ other.rotation)

    __matmul__ = compose

    def inverse(self) -> Pose:
        rt = self.rotation.T
        return Pose(-rt @ self.translation, rt)

    def apply(self, points) -> np.ndarray:
        """Map points (…, 3) from the moving frame to the reference frame."""
        return np.asarray(points, dtype=float) @ self.rotation.T + self.translation

    def rotation_angle_to(self, other: Pose) -> float:
        """Angle of the relative rotation between two poses, rad."""
        from scipy.spatial.transform import Rotation
        # Via the rotation vector: arccos of the trace loses precision below ~1e-8 rad.
        return float(Rotation.from_matrix(self.rotation.T @ other.rotation).magnitude())


def trusted_pose(translation: np.ndarray, euler: np.ndarray) -> Pose:
    """A ``Pose`` from finite (t, α, θ, γ) without ``__post_init__``'s checks (the solver's result:
    a rotation built from Euler angles is orthonormal by construction). Package-internal."""
    pose = object.__new__(Pose)
    t = np.array(translation, dtype=float)
    r = euler_to_matrix(float(euler[0]), float(euler[1]), float(euler[2]))
    t.setflags(write=False)
    r.setflags(write=False)
    object.__setattr__(pose, "translation", t)
    object.__setattr__(pose, "rotation", r)
    return pose
