"""Three crosses → 6-DOF OPR pose (method.md §3): geometry, exact forward model, solver, closed form,
rigid fits and the end-effector transform. Pure functions, SI units, frame M."""

from instrument.pose._closed_form import cross_turn, small_motion_pose
from instrument.pose._errors import (
    CrossOffScreenError,
    GeometryError,
    InconsistentCrossesError,
    MissingScreenError,
    PoseError,
    RigidFitError,
    StripeMatchError,
)
from instrument.pose._geometry import Distortion, Geometry, Screen, make_homography
from instrument.pose._lines import FANS, ScreenCross, ScreenLine, observe_cross, observe_crosses, predict_lines
from instrument.pose._rigid import RigidFit, end_effector_transform, fit_rigid_transform, tool_pose
from instrument.pose._rotation import Pose, euler_to_matrix, matrix_to_euler
from instrument.pose._solver import DEFAULT_MAX_RESIDUAL_RMS, PoseEstimate, solve_pose
from instrument.pose._synthesis import predict_measurements

__all__ = [
    "CrossOffScreenError",
    "DEFAULT_MAX_RESIDUAL_RMS",
    "Distortion",
    "FANS",
    "Geometry",
    "GeometryError",
    "InconsistentCrossesError",
    "MissingScreenError",
    "Pose",
    "PoseError",
    "PoseEstimate",
    "RigidFit",
    "RigidFitError",
    "Screen",
    "ScreenCross",
    "ScreenLine",
    "StripeMatchError",
    "cross_turn",
    "end_effector_transform",
    "euler_to_matrix",
    "fit_rigid_transform",
    "make_homography",
    "matrix_to_euler",
    "observe_cross",
    "observe_crosses",
    "predict_lines",
    "predict_measurements",
    "small_motion_pose",
    "solve_pose",
    "tool_pose",
]
