"""Rigid fits (Kabsch/Umeyama) and the end-effector composition against known transforms."""

import numpy as np
import pytest

from instrument.pose import (
    Geometry,
    Pose,
    RigidFitError,
    end_effector_transform,
    fit_rigid_transform,
    predict_measurements,
    solve_pose,
    tool_pose,
)
from tests.test_pose_station import station_dict


def random_rigid(rng):
    return Pose.from_rotvec_pose(np.r_[rng.uniform(-0.5, 0.5, 3), rng.normal(size=3)])


@pytest.mark.parametrize("count", [3, 4, 12])
def test_exact_recovery(count):
    rng = np.random.default_rng(count)
    for _ in range(10):
        truth = random_rigid(rng)
        points = rng.uniform(-0.2, 0.2, size=(count, 3))
        fit = fit_rigid_transform(points, truth.apply(points))
        np.testing.assert_allclose(fit.rotation, truth.rotation, atol=1e-12)
        np.testing.assert_allclose(fit.translation, truth.translation, atol=1e-12)
        assert fit.residual_rms < 1e-12
        assert np.linalg.det(fit.rotation) == pytest.approx(1.0)


def test_noisy_recovery_and_residual():
    rng = np.random.default_rng(8)
    truth = random_rigid(rng)
    points = rng.uniform(-0.1, 0.1, size=(50, 3))
    sigma = 1e-5
    fit = fit_rigid_transform(points, truth.apply(points) + rng.normal(0, sigma, size=points.shape))
    # 3-D residual of 50 points with 6 fitted parameters: RMS ≈ σ·sqrt(3·(50 − 2)/50).
    assert fit.residual_rms == pytest.approx(sigma * np.sqrt(3 * 48 / 50), rel=0.25)
    assert np.abs(fit.translation - truth.translation).max() < 10 * sigma
    assert truth.rotation_angle_to(fit.pose) < 10 * sigma / 0.1


def test_reflection_is_guarded():
    rng = np.random.default_rng(3)
    points = rng.uniform(-1, 1, size=(6, 3))
    mirrored = points * np.array([1.0, 1.0, -1.0])  # the best orthogonal map is a reflection
    fit = fit_rigid_transform(points, mirrored)
    assert np.linalg.det(fit.rotation) == pytest.approx(1.0)
    assert fit.residual_rms > 0.1  # a rotation cannot explain a mirror image: it says so


@pytest.mark.parametrize(
    "points_a, points_b, message",
    [
        (np.zeros((2, 3)), np.zeros((2, 3)), "at least 3 point pairs"),
        (np.eye(3), np.eye(4)[:, :3], "pair up row by row"),
        (np.eye(3)[:, :2], np.eye(3)[:, :2], r"\(n, 3\) array"),
        (
            [[0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3]],
            np.eye(4)[:, :3],
            "points_a: the points are coincident or collinear",
        ),
        (np.eye(3), [[1, 1, 1]] * 3, "points_b: the points are coincident or collinear"),
        ([[0, 0, np.nan], [1, 0, 0], [0, 1, 0]], np.eye(3), "NaN"),
        ("abc", np.eye(3), "points_a"),
    ],
)
def test_bad_inputs(points_a, points_b, message):
    with pytest.raises(RigidFitError, match=message):
        fit_rigid_transform(points_a, points_b)


def test_tool_pose_composes_opr_pose_and_tool_offset():
    rng = np.random.default_rng(12)
    opr = random_rigid(rng)
    tool_in_opr = Pose.from_rotvec_pose([0.0, 0.0, 0.15, 0.01, -0.02, 0.03])
    expected = opr.matrix @ tool_in_opr.matrix
    np.testing.assert_allclose(tool_pose(opr, tool_in_opr).matrix, expected, atol=1e-14)
    np.testing.assert_allclose(tool_pose(opr.matrix, tool_in_opr.matrix).matrix, expected, atol=1e-14)
    with pytest.raises(ValueError, match="Pose.from_rotvec_pose"):
        tool_pose(opr, [0, 0, 0.15, 0, 0, 0])


def test_end_effector_transform_then_measuring_point_from_crosses():
    """Paper §1.3: find T between {e} and {t} from mounting points, then report the tool point."""
    rng = np.random.default_rng(30)
    true_tool_in_opr = Pose.from_rotvec_pose([0.002, -0.001, 0.151, 0.004, -0.003, 0.002])
    mounting_points_e = np.array([[0.03, 0.0, 0.0], [0.0, 0.03, 0.0], [-0.02, -0.02, 0.01], [0.0, 0.0, -0.02]])
    mounting_points_t = true_tool_in_opr.apply(mounting_points_e)
    fit = end_effector_transform(mounting_points_e, mounting_points_t)
    np.testing.assert_allclose(fit.pose.matrix, true_tool_in_opr.matrix, atol=1e-12)

    geometry = Geometry.from_dict(station_dict())
    opr_truth = Pose.from_euler(rng.uniform(-0.03, 0.03, 3), np.radians(rng.uniform(-1, 1, 3)))
    estimate = solve_pose(predict_measurements(opr_truth, geometry), geometry)
    measured_tool = tool_pose(estimate, fit.pose)
    np.testing.assert_allclose(measured_tool.matrix, (opr_truth @ true_tool_in_opr).matrix, atol=1e-9)
    # The measuring point stays at the tool offset's distance from the OPR centre, whatever the pose.
    assert np.linalg.norm(measured_tool.translation - opr_truth.translation) == pytest.approx(
        np.linalg.norm(true_tool_in_opr.translation)
    )
