"""IRB 2600-class kinematics and ABB's pose conventions (mm, quaternions, confdata).

The IRB 2600-12/1.65 as published in its product specification: axis 2 at 445 mm height and
150 mm forward of axis 1, a 700 mm upper arm, axis 4 115 mm above axis 3, 795 mm from axis 3 to the
wrist centre and 85 mm from the wrist centre to the flange. ABB's joint zero is the calibration
position: upper arm vertical, forearm horizontal, tool0's z axis along the base x axis and its x
axis pointing down (quaternion ``[0.7071, 0, 0.7071, 0]``); ``theta0`` maps that onto the DH zero.

ABB speaks millimetres and unit quaternions ``[q1, q2, q3, q4] = [w, x, y, z]``; the twin's
physics speaks metres and 4×4 transforms: the converters are here, written from the RAPID
reference's definitions, not shared with any client.
"""

from __future__ import annotations

import math

import numpy as np

from sim_devices._transforms import make_transform
from sim_devices.arm import SerialArm

IRB2600 = SerialArm(
    "IRB 2600-12/1.65",
    d=[0.445, 0.0, 0.0, 0.795, 0.0, 0.085],
    a=[0.150, 0.700, 0.115, 0.0, 0.0, 0.0],
    alpha=[-np.pi / 2, 0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, 0.0],
    # Elbow up, wrist bent down by 60°: a comfortable start for the numerical inverse.
    home_seed=np.radians([0.0, 10.0, 10.0, 0.0, 60.0, 0.0]),
    theta0=[0.0, -np.pi / 2, 0.0, 0.0, 0.0, np.pi],
)

#: Axis limits of the IRB 2600 (rad): outside them the controller refuses a target.
JOINT_LIMITS = np.radians([[-180.0, 180.0], [-95.0, 155.0], [-180.0, 75.0],
                           [-400.0, 400.0], [-120.0, 120.0], [-400.0, 400.0]])


def quaternion_to_matrix(q) -> np.ndarray:
    """Rotation matrix of the quaternion ``[w, x, y, z]`` (normalised first, as RAPID does)."""
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """``[w, x, y, z]`` of a rotation matrix with w ≥ 0 (from its largest component)."""
    m = np.asarray(r, dtype=float)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > max(m[0, 0], m[1, 1], m[2, 2]):
        s = 2.0 * math.sqrt(1.0 + trace)
        q = np.array([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    elif m[0, 0] >= m[1, 1] and m[0, 0] >= m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = np.array([(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s])
    elif m[1, 1] >= m[2, 2]:
        s = 2.0 * math.sqrt(1.0 - m[0, 0] + m[1, 1] - m[2, 2])
        q = np.array([(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s])
    else:
        s = 2.0 * math.sqrt(1.0 - m[0, 0] - m[1, 1] + m[2, 2])
        q = np.array([(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s])
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def pose_from_abb(trans_mm, quaternion) -> np.ndarray:
    """4×4 transform (m) of an ABB ``pose``: translation in mm and ``[q1, q2, q3, q4]``."""
    return make_transform(quaternion_to_matrix(quaternion), np.asarray(trans_mm, dtype=float) * 1e-3)


def pose_to_abb(transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(translation in mm, quaternion ``[w, x, y, z]``) of a 4×4 transform in metres."""
    return transform[:3, 3] * 1e3, matrix_to_quaternion(transform[:3, :3])


def confdata(q) -> tuple[int, int, int, int]:
    """RAPID ``confdata`` ``[cf1, cf4, cf6, cfx]`` of joints ``q`` (rad): the quarter revolution of
    axes 1, 4 and 6, and the configuration bits (wrist flip, elbow, arm side)."""
    deg = np.degrees(np.asarray(q, dtype=float))
    cf1, cf4, cf6 = (int(math.floor(deg[i] / 90.0)) for i in (0, 3, 5))
    frames = IRB2600.joint_frames(q)
    wrist = frames[4][:3, 3]
    axis1_forward = frames[1][:3, 0]
    backwards = float(np.dot(wrist[:2] - frames[1][:2, 3], axis1_forward[:2])) < 0.0  # wrist behind axis 1
    elbow_down = deg[2] < -math.degrees(math.atan2(0.115, 0.795))  # axis 4 below the line of axes 2-3
    flipped = deg[4] < 0.0
    cfx = int(flipped) + 2 * int(elbow_down) + 4 * int(backwards)
    return cf1, cf4, cf6, cfx


def within_limits(q) -> int | None:
    """The first axis (1-based) outside its limits, or None."""
    q = np.asarray(q, dtype=float)
    outside = np.flatnonzero((q < JOINT_LIMITS[:, 0] - 1e-9) | (q > JOINT_LIMITS[:, 1] + 1e-9))
    return int(outside[0]) + 1 if len(outside) else None
