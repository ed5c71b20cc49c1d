import os
import signal
import threading
import time

import numpy as np
import pytest

from sim_devices import TwinProcess
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


# ------------------------------------------------------------------------------ the shared world of a cell
def _shared_world(tmp_path, seed=3):
    world = World(WorldConfig(seed=seed), truth_path=tmp_path / "truth.jsonl")
    world_dir = str(world.share(tmp_path / "world"))
    return world, world_dir


def _wait_for(predicate, timeout=10.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.01)


def _moved(world, dx):
    pose = world.flange_pose()
    pose[:3, 3] += dx
    return pose


def test_a_settled_change_returns_only_after_every_process_s_subscribers_saw_it(tmp_path):
    world, world_dir = _shared_world(tmp_path)
    try:
        with TwinProcess("tests._world_hosts:WorldSubscriber",
                         {"world_dir": world_dir, "seed": 3, "delay": 0.2,
                          "truth_path": str(tmp_path / "truth.jsonl")}) as other:
            # The same seed gives the same constants in every process; the state comes from the file.
            np.testing.assert_array_equal(other.call("opr_in_m"), world.opr_in_m())
            state = world.set_flange_pose(_moved(world, [0.01, 0.0, 0.0]))
            returned = time.monotonic()
            seen = {entry["seq"]: entry for entry in other.call("seen")}
            assert state.seq in seen and seen[state.seq]["settled"]
            assert seen[state.seq]["ended"] <= returned  # its (slow) subscriber had finished
            np.testing.assert_array_equal(seen[state.seq]["flange"], state.flange_pose)

            moving = world.set_flange_pose(_moved(world, [0.0, 0.01, 0.0]), settled=False)
            returned = time.monotonic()  # a moving pose does not wait for anyone
            _wait_for(lambda: any(e["seq"] == moving.seq for e in other.call("seen")))
            assert [e for e in other.call("seen") if e["seq"] == moving.seq][0]["ended"] > returned

            # A change made over there is seen here, and both processes' truth lands in one log.
            remote_seq = other.call("move", delta=[0.0, 0.0, 0.005])
            assert world.state().seq == remote_seq
            np.testing.assert_allclose(world.flange_pose()[:3, 3], moving.flange_pose[:3, 3] + [0.0, 0.0, 0.005])
            logged = world.truth.entries("pose")
            assert [e["seq"] for e in logged] == [state.seq, remote_seq]
            assert [e["source"] for e in logged] == ["robot", "subscriber"]
    finally:
        world.close()


def test_a_settled_state_overtaken_before_a_subscriber_woke_reaches_it_with_its_own_data(tmp_path):
    world, world_dir = _shared_world(tmp_path)
    try:
        with TwinProcess("tests._world_hosts:WorldSubscriber",
                         {"world_dir": world_dir, "seed": 3, "delay": 0.3}) as other:
            world.set_flange_pose(_moved(world, [0.001, 0.0, 0.0]), settled=False)  # keeps it busy for 0.3 s
            settled_done = threading.Event()
            settled_pose = _moved(world, [0.002, 0.0, 0.0])
            publisher = threading.Thread(
                target=lambda: (world.set_flange_pose(settled_pose), settled_done.set()))
            publisher.start()
            _wait_for(lambda: world.state().settled)
            settled_seq = world.state().seq
            latest = world.set_flange_pose(_moved(world, [0.003, 0.0, 0.0]), settled=False)  # overtakes it
            publisher.join(15.0)
            assert settled_done.is_set()
            _wait_for(lambda: other.call("seen")[-1]["seq"] == latest.seq)
            deliveries = {e["seq"]: e for e in other.call("seen")}
            # The settled state, with the pose it settled at (not the newer pose passed through), then
            # the newer state as what it is: moving.
            assert deliveries[settled_seq]["settled"]
            np.testing.assert_array_equal(deliveries[settled_seq]["flange"], settled_pose)
            assert not deliveries[latest.seq]["settled"]
    finally:
        world.close()


def test_the_channel_keeps_the_last_settled_record_while_moving_ones_overtake_it(tmp_path):
    world, _world_dir = _shared_world(tmp_path)
    try:
        channel = world.channel
        settled = world.set_flange_pose(_moved(world, [0.004, 0.0, 0.0]))
        for step in range(3):
            world.set_flange_pose(_moved(world, [0.0, 0.0001 * (step + 1), 0.0]), settled=False)
        current = channel.read()
        kept = channel.read_settled()
        assert current.last_settled == settled.seq and not current.settled
        assert kept.seq == settled.seq and kept.settled
        np.testing.assert_array_equal(kept.flange, settled.flange_pose)
    finally:
        world.close()


def test_announcements_reach_the_other_processes(tmp_path):
    world, world_dir = _shared_world(tmp_path)
    try:
        with TwinProcess("tests._world_hosts:WorldSubscriber", {"world_dir": world_dir, "seed": 3}) as other:
            expected = _moved(world, [0.0, 0.0, 0.02])
            world.announce(flange_pose=expected)
            _wait_for(lambda: other.call("announced"))
            np.testing.assert_array_equal(other.call("announced")[-1], expected)
            assert world.state().seq == 0  # a hint, not a change of the truth
    finally:
        world.close()


def test_a_dead_subscriber_does_not_hold_up_a_settled_change(tmp_path):
    world, world_dir = _shared_world(tmp_path)
    world.ack_timeout = 60.0
    try:
        other = TwinProcess("tests._world_hosts:WorldSubscriber", {"world_dir": world_dir, "seed": 3, "delay": 60})
        other.start()
        try:
            os.kill(other.pid, signal.SIGKILL)
            _wait_for(lambda: other.poll_exit() is not None)
            started = time.monotonic()
            world.set_flange_pose(_moved(world, [0.01, 0.0, 0.0]))
            assert time.monotonic() - started < 30.0  # not the 60 s a live subscriber would take
            assert not world.truth.entries("late_subscribers")
        finally:
            other.stop()
    finally:
        world.close()


def test_readers_never_see_a_half_written_state(tmp_path):
    world, world_dir = _shared_world(tmp_path)
    try:
        with TwinProcess("tests._world_hosts:WorldWriter", {"world_dir": world_dir, "seed": 3}) as writer:
            poses = [np.array(p) for p in writer.endpoints["poses"]]
            _wait_for(lambda: writer.call("writes") > 100)
            seqs = []
            for _ in range(100_000):  # without the seqlock, a few of these reads come out torn
                state = world.state()
                assert any(np.array_equal(state.flange_pose, p) for p in poses), "a torn read"
                seqs.append(state.seq)
            assert np.all(np.diff(seqs) >= 0) and seqs[-1] > seqs[0]
    finally:
        world.close()


def test_a_later_session_keeps_the_physics_and_draws_the_noise_anew():
    """A cell started again for the same run (a resume) is the same cell with fresh noise: it once
    replayed the first session's noise, so a calibration's repeat 2 came out bit-identical to repeat 1."""
    from sim_devices.camera import OpticalBench, Renderer

    first, again, later = (World(WorldConfig.from_dict({"seed": 3, "session": s})) for s in (0, 0, 1))
    assert first.describe()["true_opr_mount"] == later.describe()["true_opr_mount"]  # the same mounts
    assert later.describe()["session"] == 1
    assert first.rng("optics").random() == later.rng("optics").random()  # constants: every session alike
    assert first.noise_rng("ur-repeatability").random() == again.noise_rng("ur-repeatability").random()
    assert first.noise_rng("ur-repeatability").random() != later.noise_rng("ur-repeatability").random()
    # Session 0 is the noise every stream had before sessions existed.
    assert first.noise_rng("interferometer noise").random() == first.rng("interferometer noise").random()
    images = {}
    for session, world in (("first", first), ("later", later)):
        renderer = Renderer(OpticalBench(world), seed=3, session=world.config.session)
        images[session] = (renderer.render("x", world.opr_in_m(), seq=1),
                           renderer.render("x", world.opr_in_m(), seq=1, noise=False))
    assert np.array_equal(images["first"][1], images["later"][1])  # the same optics, the same ideal image
    assert not np.array_equal(images["first"][0], images["later"][0])  # other speckle and noise
    with pytest.raises(ValueError, match="session must be ≥ 0"):
        WorldConfig.from_dict({"session": -1})
