"""Rigid fits and the end-effector transform (paper §1.3, in its robust SVD form)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from instrument.pose._errors import RigidFitError
from instrument.pose._rotation import Pose


@dataclass(frozen=True)
class RigidFit:
    """points_b ≈ rotation · points_a + translation.

    Attributes
    ----------
    rotation : (3, 3) array
    translation : (3,) array
    residual_rms : float
        RMS distance of the fitted points from their partners, in the points' unit.
    residuals : (n,) array
        Per-pair distances.
    """

    rotation: np.ndarray
    translation: np.ndarray
    residual_rms: float
    residuals: np.ndarray = field(repr=False)

    @property
    def pose(self) -> Pose:
        """The fit as a Pose (T_b_a: maps frame-a coordinates to frame b)."""
        return Pose(self.translation, self.rotation)


def _points(value, name: str) -> np.ndarray:
    try:
        points = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise RigidFitError(f"{name}: expected an (n, 3) array of numbers") from None
    if points.ndim != 2 or points.shape[1] != 3:
        raise RigidFitError(f"{name}: expected an (n, 3) array, got shape {points.shape}")
    if not np.all(np.isfinite(points)):
        raise RigidFitError(f"{name}: contains NaN or infinite values")
    return points


def fit_rigid_transform(points_a, points_b, *, collinearity_tolerance: float = 1e-6) -> RigidFit:
    """Least-squares rigid transform b ≈ R·a + t (Kabsch/Umeyama SVD, no scale, no reflection).

    Parameters
    ----------
    points_a, points_b : (n, 3) arrays, n ≥ 3, corresponding rows
    collinearity_tolerance : float
        Minimum ratio of the second to the first singular value of the centred points; below it the
        points are collinear and the rotation about their line is undetermined.

    Raises
    ------
    RigidFitError
        Fewer than 3 pairs, mismatched shapes, non-finite values, coincident or collinear points.
    """
    a = _points(points_a, "points_a")
    b = _points(points_b, "points_b")
    if a.shape != b.shape:
        raise RigidFitError(f"points_a and points_b must pair up row by row, got shapes {a.shape} and {b.shape}")
    if len(a) < 3:
        raise RigidFitError(f"a rigid fit needs at least 3 point pairs, got {len(a)}")
    centroid_a, centroid_b = a.mean(axis=0), b.mean(axis=0)
    a0, b0 = a - centroid_a, b - centroid_b
    for name, centred in (("points_a", a0), ("points_b", b0)):
        singular = np.linalg.svd(centred, compute_uv=False)
        if singular[0] == 0.0 or singular[1] < collinearity_tolerance * singular[0]:
            raise RigidFitError(f"{name}: the points are coincident or collinear; the rotation is undetermined")
    u, _, vt = np.linalg.svd(b0.T @ a0)
    # Reflection guard (Umeyama): force det(R) = +1 by flipping the weakest singular direction.
    sign = np.sign(np.linalg.det(u @ vt)) or 1.0
    rotation = u @ np.diag([1.0, 1.0, sign]) @ vt
    translation = centroid_b - rotation @ centroid_a
    residuals = np.linalg.norm(a @ rotation.T + translation - b, axis=1)
    return RigidFit(rotation, translation, float(np.sqrt(np.mean(residuals**2))), residuals)


def _as_pose(value, name: str) -> Pose:
    if isinstance(value, Pose):
        return value
    array = np.asarray(value, dtype=float)
    if array.shape == (4, 4):
        return Pose.from_matrix(array)
    raise ValueError(
        f"{name}: expected a Pose or a 4×4 transform, got shape {array.shape} "
        "(for [x, y, z, rx, ry, rz] use Pose.from_rotvec_pose, for ISO [x, y, z, a, b, c] Pose.from_iso)"
    )


def tool_pose(opr_pose, tool_in_opr) -> Pose:
    """Pose of the tool's measuring point in M: T_M_E = T_M_O · T_O_E.

    Parameters
    ----------
    opr_pose : Pose, PoseEstimate or 4×4
        The OPR pose in M (``solve_pose``'s result).
    tool_in_opr : Pose or 4×4
        The measuring point in the OPR frame (station file ``frames.tool_in_opr`` via
        ``Pose.from_rotvec_pose``, or ``end_effector_transform``'s result).
    """
    opr = getattr(opr_pose, "pose", opr_pose)
    return _as_pose(opr, "opr_pose").compose(_as_pose(tool_in_opr, "tool_in_opr"))


def end_effector_transform(points_in_end_effector, points_in_opr) -> RigidFit:
    """T_t^e of the paper: from ≥ 3 mounting points known in the end-effector frame {e} and the OPR
    frame {t}; returns the fit that maps {e} coordinates into {t} (``.pose`` is T_t_e)."""
    return fit_rigid_transform(points_in_end_effector, points_in_opr)
