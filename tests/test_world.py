import numpy as np
import pytest

from sim_devices._transforms import (
    euler_to_matrix,
    matrix_to_euler,
    matrix_to_pose6,
    matrix_to_rotvec,
    pose6_to_matrix,
    rot_x,
    rot_z,
    rotvec_to_matrix,
)
from sim_devices.world import World, WorldConfig


def test_euler_convention_is_rz_ry_rx():
    alpha, theta, gamma = 0.1, -0.2, 0.3
    r = euler_to_matrix(alpha, theta, gamma)
    # Rotating e_x by Rx first leaves it; then Ry(theta) tilts it to (cos θ, 0, -sin θ); then Rz.
    expected = rot_z(gamma) @ np.array([np.cos(theta), 0.0, -np.sin(theta)])
    np.testing.assert_allclose(r[:, 0], expected, atol=1e-15)
    np.testing.assert_allclose(matrix_to_euler(r), [alpha, theta, gamma], atol=1e-14)


@pytest.mark.parametrize("rotvec", [[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [np.pi, 0.0, 0.0], [0.0, 3.1, 0.2]])
def test_rotvec_round_trip(rotvec):
    r = rotvec_to_matrix(rotvec)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(rotvec_to_matrix(matrix_to_rotvec(r)), r, atol=1e-9)


def test_opr_is_at_m_origin_at_the_reference_pose():
    world = World(WorldConfig(seed=3))
    np.testing.assert_allclose(world.opr_in_m(), np.eye(4), atol=1e-12)


def test_flange_translation_moves_opr_in_m():
    world = World(WorldConfig(seed=3))
    ref = world.reference_flange_pose
    moved = ref.copy()
    moved[:3, 3] += [0.01, 0.0, 0.0]  # 10 mm along base x
    world.set_flange_pose(moved)
    t = world.opr_in_m()[:3, 3]
    # M's x axis in B is the OPR x axis at the reference pose (flange x, tool pointing down).
    np.testing.assert_allclose(np.linalg.norm(t), 0.01, rtol=1e-12)
    expected = world.base_to_m[:3, :3].T @ np.array([0.01, 0.0, 0.0])
    np.testing.assert_allclose(t, expected, atol=1e-15)


def test_true_and_nominal_mounting_differ_realistically_and_reproducibly():
    a, b, c = World(WorldConfig(seed=1)), World(WorldConfig(seed=1)), World(WorldConfig(seed=2))
    np.testing.assert_array_equal(a.true_opr_mount, b.true_opr_mount)
    assert not np.allclose(a.true_opr_mount, c.true_opr_mount)
    offset = np.linalg.norm(a.true_opr_mount[:3, 3] - a.nominal_opr_mount[:3, 3])
    assert 1e-5 < offset < 3e-3


def test_table_mount_turns_the_opr_about_the_axis():
    world = World(WorldConfig(seed=5))
    world.mount_on_table("z")
    world.set_table_angle(np.radians(1.0))
    r = world.opr_in_m()[:3, :3]
    euler = matrix_to_euler(r)
    assert euler[2] == pytest.approx(np.radians(1.0), rel=1e-6)
    # the true axis is tilted by ~0.005°, so off-axis angles are ~tilt·angle ≈ 1e-6 rad, not zero
    assert abs(euler[0]) < 1e-5 and abs(euler[1]) < 1e-5


def test_subscribers_see_every_settled_pose_and_truth_is_logged(tmp_path):
    world = World(WorldConfig(seed=0), truth_path=tmp_path / "truth.jsonl")
    seen = []
    world.subscribe(lambda state: seen.append(state.seq))
    world.set_flange_pose(pose6_to_matrix([0.45, -0.1, 0.36, np.pi, 0, 0]))
    world.set_flange_pose(matrix_to_pose6(world.reference_flange_pose), settled=False)
    assert seen == [1, 2]
    logged = world.truth.entries("pose")
    assert [e["seq"] for e in logged] == [1]  # moving poses are not ground truth
    world.truth.close()
    lines = (tmp_path / "truth.jsonl").read_text().splitlines()
    assert len(lines) == 1 and '"opr_in_m"' in lines[0]


def test_bad_config_names_the_field():
    with pytest.raises(ValueError, match="unknown field"):
        WorldConfig.from_dict({"seed": 1, "kinematic": {}})
    with pytest.raises(ValueError, match=r"world config kinematics: unknown field\(s\) \['opr_mount_std'\]"):
        WorldConfig.from_dict({"kinematics": {"opr_mount_std": 1e-3}})
    with pytest.raises(ValueError, match="table axis"):
        World().mount_on_table("w")


def test_rot_x_is_right_handed():
    np.testing.assert_allclose(rot_x(np.pi / 2) @ [0, 1, 0], [0, 0, 1], atol=1e-15)
