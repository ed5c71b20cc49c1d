"""The physics every robot-controller twin shares: kinematics, motion profiles, paths, servos,
structural modes, the controller cycle and the dense truth record.

Written for the UR twin and moved here unchanged, with the arm (``SerialArm``) injected instead of
the UR5e built in, so the ABB twin drives the same World with the same dynamics: joint servos
(following lag, ring-down), structural modes the encoders do not see, the visit's static error
(repeatability σ, approach bias, thermal drift) and the trajectory records of the true tool.
"""

from sim_devices.arm._controller import (
    DONE_AFTER_CYCLES,
    MID_MOVE_FAULTS,
    ROBOT_MODE_POWER_OFF,
    ROBOT_MODE_RUNNING,
    RUNTIME_PLAYING,
    RUNTIME_STOPPED,
    SAFETY_BIT_ESTOP,
    SAFETY_BIT_NORMAL,
    SAFETY_BIT_PROTECTIVE,
    SAFETY_BIT_ROBOT_ESTOP,
    SAFETY_MODE_NORMAL,
    SAFETY_MODE_PROTECTIVE_STOP,
    SAFETY_MODE_ROBOT_EMERGENCY_STOP,
    ArmController,
    CycleState,
    MoveRun,
)
from sim_devices.arm._dynamics import (
    Structure,
    TruthGrid,
    matrix_to_quaternion_batch,
    rotvec_to_matrix_batch,
    small_rotvec_batch,
)
from sim_devices.arm._kinematics import IKFailed, SerialArm
from sim_devices.arm._motion import Motion, Profile
from sim_devices.arm._path import TANGENT_TOLERANCE, Arc, Blend, Line, Move, PathError, PathPlan, Run
from sim_devices.arm._servo import JointServos
from sim_devices.arm._trajectory import TrajectoryRecorder

__all__ = [
    "ROBOT_MODE_POWER_OFF", "ROBOT_MODE_RUNNING", "RUNTIME_PLAYING", "RUNTIME_STOPPED", "SAFETY_BIT_ESTOP",
    "SAFETY_BIT_NORMAL", "SAFETY_BIT_PROTECTIVE", "SAFETY_BIT_ROBOT_ESTOP", "SAFETY_MODE_NORMAL",
    "SAFETY_MODE_PROTECTIVE_STOP", "SAFETY_MODE_ROBOT_EMERGENCY_STOP",
    "DONE_AFTER_CYCLES", "MID_MOVE_FAULTS", "TANGENT_TOLERANCE", "Arc", "ArmController", "Blend", "CycleState",
    "IKFailed", "JointServos", "Line", "Motion", "Move", "MoveRun", "PathError", "PathPlan", "Profile", "Run",
    "SerialArm", "Structure", "TrajectoryRecorder", "TruthGrid", "matrix_to_quaternion_batch",
    "rotvec_to_matrix_batch", "small_rotvec_batch",
]
