"""The UR twin's structural modes, stepped by hand (no threads, no sockets): the true tool keeps
ringing after the encoders have settled, at the configured frequency and damping, lowered by the
payload; paths with blends and arcs planned as documented; the dense truth written and read back."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim_devices.faults import FaultPlan
from sim_devices.trajectory import COLUMNS, TrajectoryLog, read_trajectory
from sim_devices.ur._config import URTwinConfig
from sim_devices.ur._controller import URController
from sim_devices.ur._motion import Motion
from sim_devices.ur._path import Move, PathPlan
from sim_devices.world import World, WorldConfig

FREQUENCY_X = 12.0  # Hz, the x mode's natural frequency without payload
DAMPING_X = 0.08
QUIET = {"repeatability_translation_std": 0.0, "repeatability_rotation_std": 0.0, "thermal_drift_amplitude": 0.0,
         "approach_bias": 0.0}


def controller(tmp_path=None, **config) -> URController:
    settings = {"seed": 3, "time_scale": 1.0, **QUIET,
                "structure_frequencies": [FREQUENCY_X, 13.0, 14.5, 10.0, 11.0, 13.5],
                "structure_dampings": [DAMPING_X, 0.25, 0.3, 0.25, 0.27, 0.3], **config}
    if tmp_path is not None:
        settings["trajectory_dir"] = str(tmp_path / "trajectories")
    c = URController(World(WorldConfig(seed=3)), URTwinConfig(**settings), FaultPlan())
    c._finish = lambda run: None  # stepping by hand: no finisher thread
    return c


def move_x(c: URController, dx: float, speed: float, accel: float) -> Motion:
    target = c.tcp_pose.copy()
    target[0, 3] += dx
    return c.start_motion(lambda t, q, tcp: Motion("linear", t, q, tcp, speed=speed, accel=accel,
                                                   target_pose=target))


def ring_down(c: URController, seconds: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Step a started move through its profile, its settling and ``seconds`` more; returns the record's
    (time, true flange x), the controller time the encoders settled at and the profile's end."""
    slot = 1
    while c.run.phase in ("moving", "settling"):
        c.step(slot)
        slot += 1
        assert slot < 20_000
    settled = c.run.settled_at / c.config.time_scale
    profile_end = c.run.motion.t_end / c.config.time_scale
    for _ in range(int(seconds / c.period)):
        c.step(slot)
        slot += 1
    record = c.recorder.record(c.run.record)
    assert record is not None
    rows = record["data"]
    return rows[:, 0], rows[:, COLUMNS.index("flange_x")], settled, profile_end


def crossings(t: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Times where ``d`` changes sign (linear interpolation)."""
    i = np.nonzero(np.sign(d[:-1]) * np.sign(d[1:]) < 0)[0]
    return t[i] - d[i] * (t[i + 1] - t[i]) / (d[i + 1] - d[i])


def test_the_tool_rings_after_the_encoders_settle_at_the_configured_frequency_and_damping():
    c = controller()
    move_x(c, 0.05, 0.5, 2.5)
    t, x, settled, profile_end = ring_down(c, 2.0)
    assert np.all(np.diff(t) > 0) and np.median(np.diff(t)) == pytest.approx(1e-3)  # 1 kHz truth
    final = x[-1]
    d = x - final
    after = t > settled
    # "Done" (encoders settled) comes while the true tool is still far from its attained pose.
    assert settled - profile_end < 0.1
    assert abs(d[np.searchsorted(t, settled)]) > 2e-6
    # Free oscillation after the profile: zero crossings half a damped period apart.
    zeros = crossings(t[after], d[after])
    zeros = zeros[zeros < settled + 0.6]
    assert len(zeros) >= 6
    damped = 1.0 / (2.0 * np.mean(np.diff(zeros)))
    assert damped == pytest.approx(FREQUENCY_X * math.sqrt(1 - DAMPING_X**2), rel=0.01)
    # Successive peaks of one sign decay by exp(−ζ ω T_d): the logarithmic decrement gives ζ.
    peaks = [np.max(np.abs(d[(t > a) & (t < b)])) for a, b in zip(zeros[:-1], zeros[1:])]
    decrement = np.log(peaks[0] / peaks[2]) / 1.0  # two half periods = one damped period
    zeta = decrement / math.sqrt(4 * math.pi**2 + decrement**2)
    assert zeta == pytest.approx(DAMPING_X, rel=0.1)
    # And it dies out with that envelope: 1.6 s after the first peak, below exp(−ζω·1.6 s) of it (×2).
    assert np.max(np.abs(d[t > t[-1] - 0.2])) < 2 * peaks[0] * math.exp(-DAMPING_X * 2 * math.pi * FREQUENCY_X * 1.6)


def test_a_payload_lowers_the_frequency_and_raises_the_residual_vibration():
    figures = {}
    for mass in (0.0, 5.0):  # 5 kg = structure_payload_reference: ω / √2
        c = controller(structure_payload_reference=5.0)
        c.set_payload(mass)
        move_x(c, 0.05, 0.5, 2.5)
        t, x, settled, _ = ring_down(c, 1.0)
        d = x - x[-1]
        after = t > settled
        zeros = crossings(t[after], d[after])[:6]
        figures[mass] = (1.0 / (2.0 * np.mean(np.diff(zeros))), float(np.max(np.abs(d[after]))))
    assert figures[0.0][0] / figures[5.0][0] == pytest.approx(math.sqrt(2.0), rel=0.02)
    assert figures[5.0][1] > 1.2 * figures[0.0][1]


def test_the_residual_vibration_grows_with_the_test_speed():
    """ISO 9283's 10 % / 100 % rated-speed tests scale speed and acceleration together: the sag the
    structure held against the deceleration, released when the profile ends, grows with them (at a
    fixed acceleration, speed enters only through the small lag ``structure_lag · v``)."""
    amplitude = {}
    for share in (0.1, 1.0):
        c = controller()
        move_x(c, 0.08, 0.5 * share, 2.5 * share)
        t, x, settled, profile_end = ring_down(c, 0.8)
        d = x - x[-1]
        amplitude[share] = float(np.max(np.abs(d[t > profile_end])))
    assert amplitude[1.0] > 3 * amplitude[0.1]


def test_without_structure_the_truth_is_the_encoders_plus_the_static_error(tmp_path):
    c = controller(tmp_path, structure_dynamics=False)
    move_x(c, 0.02, 0.25, 1.2)
    t, x, settled, _ = ring_down(c, 0.2)
    assert np.max(np.abs(x[t > settled] - x[-1])) < 1e-12
    record = read_trajectory(next((tmp_path / "trajectories").glob("move-*.traj")))
    assert not record.closed and len(record.rows) > 0  # still open: rows already on disk, no summary yet
    # No static error configured: the true tool is where the encoders say, exactly.
    np.testing.assert_allclose(record.true_tcp()[:, :3, 3], record.encoder_tcp()[:, :3, 3], atol=1e-12)


def test_the_trajectory_file_round_trips_and_the_log_interpolates(tmp_path):
    c = controller(tmp_path)
    start_flange = c.true_flange.copy()
    move_x(c, 0.03, 0.3, 2.0)
    ring_down(c, 0.3)
    c.run = None  # as the finisher would: the record closes once the residual is below a nanometre
    slot = c.cycle + 1
    while c.recorder.is_open:
        c.step(slot)
        slot += 1
        assert slot < 10_000
    log = TrajectoryLog(tmp_path / "trajectories")
    (record,) = log.records()
    assert record.closed and record.meta["kind"] == "linear" and record.meta["rows"] == len(record.rows)
    assert log.known_until() == math.inf
    # Between two samples: linear in position; before the record: the rest pose; after: the last sample.
    t = record.time
    mid = 0.5 * (t[100] + t[101])
    np.testing.assert_allclose(log.flange_at([mid])[0][:3, 3], 0.5 * (record.rows[100, 1:4] + record.rows[101, 1:4]),
                               atol=1e-12)
    np.testing.assert_allclose(log.flange_at([t[0] - 1.0], rest=start_flange)[0], start_flange)
    np.testing.assert_allclose(log.flange_at([t[-1] + 5.0])[0], record.flange()[-1], atol=1e-12)
    times, poses = log.samples(t[10], t[20])
    assert len(times) == 11 and poses.shape == (11, 4, 4)


def test_a_blended_corner_passes_at_half_the_radius_times_sin_of_half_the_turn():
    start = np.eye(4)
    start[:3, 3] = [0.4, 0.0, 0.3]
    corner, end = start.copy(), start.copy()
    corner[:3, 3] += [0.05, 0.0, 0.0]
    end[:3, 3] = corner[:3, 3] + [0.0, 0.04, 0.0]
    r = 0.01
    plan = PathPlan(start, [Move("linear", corner, 0.2, 1.5, r), Move("linear", end, 0.2, 1.5, 0.0)])
    assert len(plan.runs) == 1  # no stop at the corner
    run = plan.runs[0]
    s = np.linspace(0.0, run.length, 4001)
    points = np.array([run.position(v) for v in s])
    closest = np.min(np.linalg.norm(points - corner[:3, 3], axis=1))
    assert closest == pytest.approx(0.5 * r * math.sin(math.pi / 4), rel=1e-3)
    assert run.length == pytest.approx(0.05 + 0.04 - 2 * r + plan.runs[0].pieces[1].length, rel=1e-9)
    # The run's speed is limited by the turn: v² ≤ a · r · cos²(φ/2) / sin(φ/2).
    assert run.speed == pytest.approx(min(0.2, math.sqrt(1.5 * r * 0.5 / math.sin(math.pi / 4))))
    # Without a blend the robot stops at the corner: two runs.
    assert len(PathPlan(start, [Move("linear", corner, 0.2, 1.5, 0.0), Move("linear", end, 0.2, 1.5)]).runs) == 2
