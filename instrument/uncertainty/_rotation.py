"""Vectorised pose arithmetic for the Monte Carlo: Euler angles ↔ matrices, composition.

Conventions as in method.md §3: a pose row is [x, y, z, a, b, c] (m, rad) with
R = Rz(c)·Ry(b)·Rx(a). Every function works on stacks (..., 6) so that one call handles all
Monte Carlo draws of all poses of a point; ``instrument.pose.Pose`` does the same one pose at a time.
"""

from __future__ import annotations

import numpy as np


def euler_to_matrix(angles: np.ndarray) -> np.ndarray:
    """(..., 3) Euler angles (a, b, c) → (..., 3, 3) rotation matrices Rz(c)·Ry(b)·Rx(a)."""
    a, b, c = np.moveaxis(np.asarray(angles, dtype=float), -1, 0)
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    rows = [
        [cc * cb, cc * sb * sa - sc * ca, cc * sb * ca + sc * sa],
        [sc * cb, sc * sb * sa + cc * ca, sc * sb * ca - cc * sa],
        [-sb, cb * sa, cb * ca],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def matrix_to_euler(matrix: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices → (..., 3) Euler angles (a, b, c), |b| < π/2."""
    m = np.asarray(matrix, dtype=float)
    a = np.arctan2(m[..., 2, 1], m[..., 2, 2])
    b = np.arctan2(-m[..., 2, 0], np.hypot(m[..., 0, 0], m[..., 1, 0]))
    c = np.arctan2(m[..., 1, 0], m[..., 0, 0])
    return np.stack([a, b, c], axis=-1)


def as_transform(pose) -> tuple[np.ndarray, np.ndarray]:
    """A (6,) pose row or a 4×4 homogeneous matrix → (rotation 3×3, translation (3,))."""
    array = np.asarray(pose, dtype=float)
    if array.shape == (4, 4):
        return array[:3, :3].copy(), array[:3, 3].copy()
    if array.shape == (6,):
        return euler_to_matrix(array[3:]), array[:3].copy()
    raise ValueError(f"expected a (6,) pose [x, y, z, a, b, c] or a 4×4 matrix, got shape {array.shape}")


def compose(poses: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Pose rows (..., 6) of frame O in M, composed with a fixed transform T_O_E → rows of E in M."""
    poses = np.asarray(poses, dtype=float)
    r_mo = euler_to_matrix(poses[..., 3:])
    position = poses[..., :3] + np.einsum("...ij,j->...i", r_mo, translation)
    return np.concatenate([position, matrix_to_euler(r_mo @ rotation)], axis=-1)


def decompose(poses: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Inverse of ``compose``: rows of E in M and T_O_E → rows of O in M."""
    inverse_rotation = rotation.T
    return compose(poses, inverse_rotation, -inverse_rotation @ translation)
