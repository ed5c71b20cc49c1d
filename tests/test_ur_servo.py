"""The UR twin's controller stepped by hand (no threads, no sockets): servo lag, settling, the cycle's
one state, the attained pose announced before the move and published before 'done'."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from sim_devices._transforms import pose6_to_matrix
from sim_devices.faults import FaultPlan
from sim_devices.ur import _kinematics as kin
from sim_devices.ur._config import URTwinConfig
from sim_devices.ur._controller import URController
from sim_devices.ur._motion import Motion
from sim_devices.ur._servo import JointServos
from sim_devices.world import World, WorldConfig


def controller(**config) -> tuple[URController, World]:
    world = World(WorldConfig(seed=1))
    return URController(world, URTwinConfig(seed=1, **config), FaultPlan()), world


def linear_move(c: URController, dx: float, speed: float, accel: float = 1.2) -> Motion:
    target = c.tcp_pose.copy()
    target[0, 3] += dx
    return c.start_motion(lambda t, q, tcp: Motion("linear", t, q, tcp, speed=speed, accel=accel,
                                                   target_pose=target))


def run_until_at_rest(c: URController, first_slot: int, limit: int = 20_000) -> list[dict]:
    """Step cycles until the move is handed over (at rest); returns every cycle's fields."""
    fields = []
    slot = first_slot
    while c.run is not None and c.run.phase in ("moving", "settling"):
        assert slot < first_slot + limit, "the move never came to rest"
        fields.append(c.step(slot).fields)
        slot += 1
    return fields


def test_servo_lags_by_tau_times_speed_at_constant_speed():
    servos = JointServos(40.0, 0.8, 0.002, 0.1, np.random.default_rng(0))
    error, rate = np.zeros(6), np.zeros(6)
    velocity = np.array([0.1, -0.2, 0.3, 0.0, 0.05, -0.4])
    for _ in range(500):  # 1 s of 2 ms steps at constant speed
        error, rate = servos.step(error, rate, velocity, np.zeros(6), 0.002)
    np.testing.assert_allclose(error, -0.002 * velocity, rtol=1e-9, atol=1e-15)
    # The exact step does not care how long a step is: one 1 s step lands on the same state.
    big_error, _ = servos.step(np.zeros(6), np.zeros(6), velocity, np.zeros(6), 1.0)
    np.testing.assert_allclose(big_error, error, rtol=1e-6, atol=1e-15)


def test_servo_rings_down_after_a_stop_and_its_joints_differ_reproducibly():
    servos = JointServos(40.0, 0.8, 0.002, 0.1, np.random.default_rng(0))
    again = JointServos(40.0, 0.8, 0.002, 0.1, np.random.default_rng(0))
    np.testing.assert_array_equal(servos.omega, again.omega)
    assert np.ptp(servos.omega) > 0  # seeded spread between joints
    error, rate = np.full(6, 1e-4), np.zeros(6)
    trace = []
    for _ in range(200):
        error, rate = servos.step(error, rate, np.zeros(6), np.zeros(6), 0.0005)
        trace.append(error[0])
    trace = np.array(trace)
    assert np.any(trace < 0)  # it overshoots (underdamped) ...
    assert abs(trace[-1]) < 1e-4 * np.exp(-servos.sigma[0] * 0.1) * 3  # ... and decays as exp(−ζωt)
    assert servos.settled(error, rate, 1e-6) == bool(np.all(np.hypot(error, rate / servos.omega) < 1e-6))


def test_following_error_grows_with_speed_and_the_move_ends_at_rest():
    lags = {}
    for speed in (0.05, 0.2):
        c, _ = controller(time_scale=1.0)
        c._finish = lambda run: None  # stepping by hand: no finisher thread here
        linear_move(c, 0.2, speed)
        fields = run_until_at_rest(c, 1)
        cruising = [f for f in fields if abs(np.linalg.norm(f["target_TCP_speed"][:3]) - speed) < 1e-9]
        late = cruising[len(cruising) // 2:]  # the ramp's transient has died out by then
        gaps = [np.linalg.norm(np.subtract(f["actual_TCP_pose"][:3], f["target_TCP_pose"][:3])) for f in late]
        lags[speed] = float(np.median(gaps))
        # While cruising the lag is τ × speed (1 ms by default).
        assert lags[speed] == pytest.approx(0.001 * speed, rel=0.05)
        assert c.run.phase == "finishing"
        np.testing.assert_array_equal(c.q + c.error, c.q)  # at rest, actual is exactly target
        np.testing.assert_allclose(c.actual_tcp_pose, c.tcp_pose, atol=0)
        assert c.run.settled_at > c.run.motion.t_end  # it settled after the profile, not at its end
    assert lags[0.2] == pytest.approx(4 * lags[0.05], rel=0.05)


def test_an_ideal_servo_reports_actual_equal_to_target_and_settles_at_the_profile_end():
    c, _ = controller(servo_dynamics=False)
    c._finish = lambda run: None
    linear_move(c, 0.05, 0.25)
    for f in run_until_at_rest(c, 1):
        assert f["actual_q"] == f["target_q"] and f["actual_TCP_pose"] == f["target_TCP_pose"]
    assert c.run.settled_at - c.run.motion.t_end < 0.002 + 1e-12


def test_each_cycle_reports_one_consistent_state():
    c, _ = controller(time_scale=5.0)
    c._finish = lambda run: None
    linear_move(c, 0.1, 0.25)
    previous = None
    for f in run_until_at_rest(c, 1):
        for joints, pose in (("actual_q", "actual_TCP_pose"), ("target_q", "target_TCP_pose")):
            np.testing.assert_allclose(kin.forward(f[joints]), pose6_to_matrix(f[pose]), atol=1e-9)
        if previous is not None:
            assert f["timestamp"] == pytest.approx(previous["timestamp"] + 0.002)  # controller seconds
        previous = f
    # Currents hold the arm against gravity; the force estimate is small noise around zero.
    assert abs(previous["target_current"][1]) > 0.5
    assert np.linalg.norm(previous["actual_TCP_force"][:3]) < 5.0


def test_the_attained_pose_is_announced_when_planned_and_published_before_done():
    c, world = controller(time_scale=10.0)
    announced, published = [], []
    world.on_announce(lambda expected: announced.append(expected.flange_pose))
    world.subscribe(lambda state: published.append((state.settled, state.flange_pose, c.run)))
    motion = linear_move(c, 0.02, 0.25)
    assert len(announced) == 1  # at planning time, before any cycle ran
    run = c.run
    fields = run_until_at_rest(c, 1)
    for slot in range(len(fields) + 1, len(fields) + 7):  # the arm rests a few cycles before 'done' goes out
        c.step(slot)
    c._finish(run)  # what the finisher thread does once the move is at rest
    settled = [flange for is_settled, flange, _ in published if is_settled]
    assert len(settled) == 1
    np.testing.assert_array_equal(settled[0], announced[0])  # bit for bit: the cameras' early frames fit
    assert all(r is run for _, _, r in published)  # the world heard it while the move was still running ...
    assert run.done.is_set() and c.run is None  # ... and only then was it done
    visit = c.visits[-1]
    assert not visit["stopped"] and visit["settling_time"] > 0
    # The attained pose is the commanded one plus the hidden repeatability error (~10 µm), never equal.
    error = np.linalg.norm(np.subtract(visit["attained_tcp"][:3], visit["commanded_tcp"][:3]))
    assert 1e-7 < error < 1e-4
    np.testing.assert_allclose(visit["commanded_tcp"], kin.forward_pose(c.q), atol=1e-12)
    assert motion.target_pose[0, 3] == pytest.approx(visit["commanded_tcp"][0])


def test_a_late_cycle_thread_makes_up_every_slot():
    """Woken 15 slots late, the cycle thread sends every missed slot (back to back), not just the current one."""
    c, _ = controller()
    sent: list[int] = []
    enough = threading.Event()

    def listener(state):
        sent.append(state.cycle)
        if len(sent) >= 40:
            enough.set()

    c.add_cycle_listener(listener)
    c._wall0 = time.monotonic() - 0.030
    thread = threading.Thread(target=c._run, daemon=True)
    thread.start()
    try:
        assert enough.wait(10.0)
    finally:
        c._stop.set()
        thread.join(2.0)
    assert sent[:40] == list(range(40)) or c.skipped_cycles > 0  # a resync is counted, never silent
    assert c.late_cycles > 0
