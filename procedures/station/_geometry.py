"""Small pose helpers for the procedure layer (4×4 transforms, UR poses, the paper's Euler angles).

Poses in M are ``(6,)`` ``[x, y, z, alpha, theta, gamma]`` with R = Rz(gamma)·Ry(theta)·Rx(alpha)
(scipy's extrinsic "xyz"); robot poses are UR ``[x, y, z, rx, ry, rz]`` (rotation vector).
"""

from __future__ import annotations

import numpy as np

ANGLE_COMPONENT = {"x": "a", "y": "b", "z": "c"}  # the pose component of a rotation about M's axis k


def ur_to_matrix(pose) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    pose = np.asarray(pose, dtype=float)
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(pose[3:]).as_matrix()
    out[:3, 3] = pose[:3]
    return out


def matrix_to_ur(matrix: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    return np.concatenate([matrix[:3, 3], Rotation.from_matrix(matrix[:3, :3]).as_rotvec()])


def euler_to_matrix(pose) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    pose = np.asarray(pose, dtype=float)
    out = np.eye(4)
    out[:3, :3] = Rotation.from_euler("xyz", pose[3:]).as_matrix()
    out[:3, 3] = pose[:3]
    return out


def matrix_to_euler(matrix: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    return np.concatenate([matrix[:3, 3], Rotation.from_matrix(matrix[:3, :3]).as_euler("xyz")])


def translated_in_frame(reference_pose, offset_in_frame) -> np.ndarray:
    """UR pose ``reference_pose`` moved by ``offset_in_frame`` (3,), expressed along the
    reference pose's own axes; orientation unchanged."""
    reference = ur_to_matrix(reference_pose)
    target = reference.copy()
    target[:3, 3] = reference[:3, 3] + reference[:3, :3] @ np.asarray(offset_in_frame, dtype=float)
    return matrix_to_ur(target)


def tcp_in_m(reference_pose, tcp_pose) -> np.ndarray:
    """The pose (4×4) of the TCP (the OPR) in the nominal M: ``inv(T_B_ref) @ T_B_tcp``."""
    return np.linalg.inv(ur_to_matrix(reference_pose)) @ ur_to_matrix(tcp_pose)
