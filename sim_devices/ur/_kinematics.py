"""UR5e-class kinematics for the controller twin: the published DH table on ``sim_devices.arm.SerialArm``.

Standard Denavit–Hartenberg parameters of the UR5e as published by Universal Robots. The forward
kinematics gives the flange (tool0) pose in the base frame; a TCP offset ``T_F_TCP`` is composed on
the right. The inverse is a damped Newton iteration started from ``qnear`` (the current joints by
default), so it returns the solution in the same configuration branch, which is what a controller's
``get_inverse_kin`` does when given a near solution. The module-level functions are the UR5e arm's
methods, so the UR twin's code reads as before.
"""

from __future__ import annotations

import numpy as np

from sim_devices._transforms import matrix_to_pose6, pose6_to_matrix
from sim_devices.arm import IKFailed, SerialArm

#: UR5e DH parameters (metres, radians).
UR5E_D = np.array([0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996])
UR5E_A = np.array([0.0, -0.425, -0.3922, 0.0, 0.0, 0.0])
UR5E_ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])

#: A comfortable "elbow up, wrist down" seed used to find the start-up joints.
HOME_SEED = np.array([np.pi, -1.9, 1.9, -1.57, -1.57, 0.0])

UR5E = SerialArm("UR5e", UR5E_D, UR5E_A, UR5E_ALPHA, HOME_SEED)

joint_frames = UR5E.joint_frames
forward = UR5E.forward
forward_pose = UR5E.forward_pose
inverse = UR5E.inverse
flange_from_tcp = SerialArm.flange_from_tcp

__all__ = ["HOME_SEED", "UR5E", "UR5E_A", "UR5E_ALPHA", "UR5E_D", "IKFailed", "flange_from_tcp", "forward",
           "forward_pose", "inverse", "joint_frames", "pose_trans"]


def pose_trans(p_from, p_from_to) -> np.ndarray:
    """URScript ``pose_trans``: ``p_from ∘ p_from_to`` as a UR pose."""
    return matrix_to_pose6(pose6_to_matrix(p_from) @ pose6_to_matrix(p_from_to))
