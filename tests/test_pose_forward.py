"""The exact forward model (fan planes ∩ screens) and the Pose type, against hand computations."""

import numpy as np
import pytest

from instrument.pose import Geometry, Pose, PoseError, euler_to_matrix, matrix_to_euler, predict_lines
from tests.test_pose_station import station_dict

GEOMETRY = Geometry.from_dict(station_dict())
RNG_SEED = 20231


def test_identity_pose_draws_crosses_on_the_screen_origins_along_u_and_v():
    lines = predict_lines(Pose.identity(), GEOMETRY)
    for screen, (first, second) in {"x": ("xy", "xz"), "y": ("yz", "yx"), "z": ("zx", "zy")}.items():
        np.testing.assert_allclose(lines[screen][first].direction, [1, 0], atol=1e-15)
        np.testing.assert_allclose(lines[screen][second].direction, [0, 1], atol=1e-15)
        np.testing.assert_allclose(lines[screen][first].point, [0, 0], atol=1e-15)
        np.testing.assert_allclose(lines[screen][second].point, [0, 0], atol=1e-15)


def test_pure_translation_shifts_each_cross_by_the_in_plane_components():
    t = np.array([0.012, -0.034, 0.021])
    lines = predict_lines(Pose(t, np.eye(3)), GEOMETRY)
    # screen x: (u, v) = (y, z); the "xy" stripe is the line v = t_z, the "xz" stripe u = t_y.
    assert lines["x"]["xy"].distance([[0.0, t[2]]])[0] == pytest.approx(0.0, abs=1e-15)
    assert lines["x"]["xz"].distance([[t[1], 0.0]])[0] == pytest.approx(0.0, abs=1e-15)
    # screen y: (u, v) = (z, x); screen z: (u, v) = (x, y).
    assert lines["y"]["yz"].distance([[0.0, t[0]]])[0] == pytest.approx(0.0, abs=1e-15)
    assert lines["y"]["yx"].distance([[t[2], 0.0]])[0] == pytest.approx(0.0, abs=1e-15)
    assert lines["z"]["zx"].distance([[0.0, t[1]]])[0] == pytest.approx(0.0, abs=1e-15)
    assert lines["z"]["zy"].distance([[t[0], 0.0]])[0] == pytest.approx(0.0, abs=1e-15)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_rotation_about_axis_k_turns_the_cross_on_screen_k_by_the_same_positive_angle(axis):
    angle = np.radians(1.7)
    euler = np.zeros(3)
    euler[axis] = angle
    lines = predict_lines(Pose.from_euler(np.zeros(3), euler), GEOMETRY)
    screen = "xyz"[axis]
    first, second = {"x": ("xy", "xz"), "y": ("yz", "yx"), "z": ("zx", "zy")}[screen]
    np.testing.assert_allclose(lines[screen][first].direction, [np.cos(angle), np.sin(angle)], atol=1e-15)
    np.testing.assert_allclose(lines[screen][second].direction, [-np.sin(angle), np.cos(angle)], atol=1e-15)


def test_rotation_about_x_moves_the_y_cross_along_z_by_l_tan_alpha():
    alpha = np.radians(0.8)
    lines = predict_lines(Pose.from_euler(np.zeros(3), [alpha, 0, 0]), GEOMETRY)
    # beam R·e_y = (0, cos α, sin α) meets y = 0.25 at z = 0.25·tan α; screen y's u axis is z.
    assert lines["y"]["yx"].distance([[0.25 * np.tan(alpha), 0.0]])[0] == pytest.approx(0.0, abs=1e-15)
    assert lines["y"]["yz"].distance([[0.25 * np.tan(alpha), 0.0]])[0] == pytest.approx(0.0, abs=1e-15)


def test_random_poses_lines_lie_in_both_planes_and_cross_at_the_beam():
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(20):
        pose = Pose.from_euler(rng.uniform(-0.05, 0.05, 3), np.radians(rng.uniform(-5, 5, 3)))
        lines = predict_lines(pose, GEOMETRY)
        for screen_name, fans in lines.items():
            screen = GEOMETRY.screens[screen_name]
            k = "xyz".index(screen_name)
            beam = pose.rotation[:, k]
            hit = pose.translation + (screen.origin[k] - pose.translation[k]) / beam[k] * beam  # ray ∩ plane
            for fan, line in fans.items():
                j = 3 - "xyz".index(fan[0]) - "xyz".index(fan[1])
                normal = pose.rotation[:, j]
                samples = line.point + np.outer([-0.05, 0.0, 0.07], line.direction)
                points = screen.to_frame(samples)
                np.testing.assert_allclose((points - pose.translation) @ normal, 0.0, atol=1e-15)
                np.testing.assert_allclose((points - screen.origin) @ screen.normal, 0.0, atol=1e-15)
                # oriented along the OPR axis the fan contains
                along = line.direction[0] * screen.u + line.direction[1] * screen.v
                assert along @ pose.rotation[:, "xyz".index(fan[1])] > 0
                # the beam's hit point lies on both stripes
                hit_uv = [(hit - screen.origin) @ screen.u, (hit - screen.origin) @ screen.v]
                assert abs(line.distance([hit_uv])[0]) < 1e-15


def test_fan_parallel_to_screen_is_an_error():
    with pytest.raises(PoseError, match="parallel to screen"):
        predict_lines(Pose.from_euler(np.zeros(3), [0, 0, np.pi / 2]), GEOMETRY)


def test_euler_convention_is_the_papers_equation_4():
    a, t, g = 0.3, -0.2, 0.7
    ca, sa, ct, st, cg, sg = np.cos(a), np.sin(a), np.cos(t), np.sin(t), np.cos(g), np.sin(g)
    paper = np.array(
        [
            [cg * ct, cg * st * sa - sg * ca, cg * st * ca + sg * sa],
            [sg * ct, sg * st * sa + cg * ca, sg * st * ca - cg * sa],
            [-st, ct * sa, ct * ca],
        ]
    )
    np.testing.assert_allclose(euler_to_matrix(a, t, g), paper, atol=1e-15)
    np.testing.assert_allclose(matrix_to_euler(paper), [a, t, g], atol=1e-15)


def test_pose_algebra():
    rng = np.random.default_rng(3)
    first = Pose.from_euler(rng.normal(size=3), rng.normal(size=3) * 0.5)
    second = Pose.from_rotvec_pose(np.r_[rng.normal(size=3), rng.normal(size=3) * 0.5])
    np.testing.assert_allclose((first @ second).matrix, first.matrix @ second.matrix, atol=1e-14)
    np.testing.assert_allclose((first @ first.inverse()).matrix, np.eye(4), atol=1e-14)
    np.testing.assert_allclose(Pose.from_iso(first.as_iso()).matrix, first.matrix, atol=1e-14)
    np.testing.assert_allclose(Pose.from_rotvec_pose(second.as_rotvec_pose()).matrix, second.matrix, atol=1e-14)
    np.testing.assert_allclose(Pose.from_matrix(first.matrix).apply([1, 2, 3]), first.matrix[:3] @ [1, 2, 3, 1])
    assert first.rotation_angle_to(first) == 0.0


@pytest.mark.parametrize(
    "translation, rotation, message",
    [
        ([0, 0, np.nan], np.eye(3), "translation"),
        ([0, 0], np.eye(3), "translation"),
        ([0, 0, 0], np.diag([1.0, 1.0, -1.0]), "not a proper rotation"),
        ([0, 0, 0], np.eye(3) * 1.01, "not a proper rotation"),
    ],
)
def test_pose_rejects_bad_values(translation, rotation, message):
    with pytest.raises(ValueError, match=message):
        Pose(translation, rotation)
