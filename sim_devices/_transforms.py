"""Rigid transforms for the simulated world.

Written independently of ``instrument`` on purpose: the twins' physics and the measurement core
must not share convention code, so that a convention error on either side fails a test.

Conventions: 4×4 homogeneous matrices ``T_a_b`` map coordinates in frame b to frame a. Euler
angles (alpha, theta, gamma) mean R = Rz(gamma) @ Ry(theta) @ Rx(alpha). UR poses are
``[x, y, z, rx, ry, rz]`` with a rotation vector.
"""

from __future__ import annotations

import math

import numpy as np

ARCSEC = np.pi / (180.0 * 3600.0)
"""One arc-second in radians (the twins' own: they never import ``instrument``)."""


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
    """R = Rz(gamma) @ Ry(theta) @ Rx(alpha)."""
    return rot_z(gamma) @ rot_y(theta) @ rot_x(alpha)


def matrix_to_euler(rotation: np.ndarray) -> np.ndarray:
    """Inverse of ``euler_to_matrix`` for |theta| < pi/2: returns (alpha, theta, gamma)."""
    r = np.asarray(rotation, dtype=float)
    theta = np.arcsin(np.clip(-r[2, 0], -1.0, 1.0))
    alpha = np.arctan2(r[2, 1], r[2, 2])
    gamma = np.arctan2(r[1, 0], r[0, 0])
    return np.array([alpha, theta, gamma])


def rotvec_to_matrix(rotvec) -> np.ndarray:
    """Rodrigues' formula."""
    v = np.asarray(rotvec, dtype=float)
    angle = float(np.linalg.norm(v))
    if angle < 1e-15:
        return np.eye(3)
    k = v / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * (kx @ kx)


def matrix_to_rotvec(rotation: np.ndarray) -> np.ndarray:
    """Rotation vector (angle in [0, π]) of a rotation matrix, accurate at every angle.

    Through the unit quaternion (Shepperd's method: built from the largest of its four components,
    so no component is recovered from a difference of nearly equal numbers): near π the
    antisymmetric part of the matrix vanishes and the textbook formula loses the axis's sign and
    most of its digits.
    """
    # On Python floats (the twins' cycles call this hundreds of times a second; numpy scalars are slow).
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = np.asarray(rotation, dtype=float)[:3, :3].tolist()
    trace = r00 + r11 + r22
    if trace >= r00 and trace >= r11 and trace >= r22:  # np.argmax's choice: the first of the largest
        w = 0.5 * math.sqrt(max(1.0 + trace, 0.0))
        four = 4.0 * w
        x, y, z = (r21 - r12) / four, (r02 - r20) / four, (r10 - r01) / four
    elif r00 >= r11 and r00 >= r22:
        x = 0.5 * math.sqrt(max(1.0 + r00 - r11 - r22, 0.0))
        four = 4.0 * x
        y, z, w = (r10 + r01) / four, (r20 + r02) / four, (r21 - r12) / four
    elif r11 >= r22:
        y = 0.5 * math.sqrt(max(1.0 + r11 - r22 - r00, 0.0))
        four = 4.0 * y
        z, x, w = (r21 + r12) / four, (r01 + r10) / four, (r02 - r20) / four
    else:
        z = 0.5 * math.sqrt(max(1.0 + r22 - r00 - r11, 0.0))
        four = 4.0 * z
        x, y, w = (r02 + r20) / four, (r12 + r21) / four, (r10 - r01) / four
    if w < 0:  # the same rotation; this sign keeps the angle in [0, π]
        w, x, y, z = -w, -x, -y, -z
    norm = math.sqrt(x * x + y * y + z * z)
    if norm < 1e-300:
        return np.zeros(3)
    scale = 2.0 * math.atan2(norm, w) / norm
    return np.array([x * scale, y * scale, z * scale])


def make_transform(rotation: np.ndarray | None = None, translation=None) -> np.ndarray:
    t = np.eye(4)
    if rotation is not None:
        t[:3, :3] = rotation
    if translation is not None:
        t[:3, 3] = np.asarray(translation, dtype=float)
    return t


def pose6_to_matrix(pose) -> np.ndarray:
    """UR pose [x, y, z, rx, ry, rz] → 4×4."""
    p = np.asarray(pose, dtype=float).reshape(6)
    return make_transform(rotvec_to_matrix(p[3:]), p[:3])


def matrix_to_pose6(transform: np.ndarray) -> np.ndarray:
    return np.concatenate([transform[:3, 3], matrix_to_rotvec(transform[:3, :3])])


def invert(transform: np.ndarray) -> np.ndarray:
    r = transform[:3, :3]
    out = np.eye(4)
    out[:3, :3] = r.T
    out[:3, 3] = -r.T @ transform[:3, 3]
    return out


def small_random_transform(rng: np.random.Generator, translation_std: float, rotation_std: float) -> np.ndarray:
    """A transform with normally distributed translation (m) and rotation-vector (rad) errors."""
    return make_transform(
        rotvec_to_matrix(rng.normal(0.0, rotation_std, 3)), rng.normal(0.0, translation_std, 3)
    )
