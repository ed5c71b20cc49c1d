"""``URRobot``'s moves for measuring in motion (``move_path``, ``move_circular``, ``is_steady``,
``controller_time``, ``last_move_done_time``) through the real ur_rtde clients against the UR twin
in its own process, checked on the twin's dense truth (its trajectory files).

Twins here use 127.0.0.150 … 127.0.0.169.
"""

from __future__ import annotations

import itertools
import math
import time

import numpy as np
import pytest

from drivers import DeviceConnectionError, DeviceTimeout, MotionRefused
from drivers.robot import MotionEnvelope, create
from sim_devices import TwinProcess
from sim_devices.cell import free_loopback_host
from sim_devices.trajectory import Trajectory, TrajectoryLog

pytest.importorskip("rtde_control")

TCP = np.array([0.0, 0.0, 0.08, 0.0, 0.0, 0.0])
REFERENCE = np.array([0.45, -0.10, 0.35 - 0.08, np.pi, 0.0, 0.0])  # TCP at the reference flange pose
ENVELOPE = MotionEnvelope.from_dict({"box_min": [0.25, -0.35, 0.10], "box_max": [0.70, 0.25, 0.60],
                                     "max_tilt": 0.6, "max_speed": 1.0, "max_acceleration": 3.0})
QUIET = {"repeatability_translation_std": 0.0, "repeatability_rotation_std": 0.0, "thermal_drift_amplitude": 0.0,
         "approach_bias": 0.0}
_addresses = itertools.count(150)

# The done time a driver reports is the controller's clock (the host's would be off by the twin's whole
# uptime), read from the first package its worker saw done: a starved host reads that package late (30 ms
# late was seen once in a full run), never early.
_DONE_LATE_BY = 0.25


def free_address() -> str:
    return free_loopback_host(first=next(_addresses), last=169)


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    directory = tmp_path_factory.mktemp("ur-dynamic") / "trajectories"
    process = TwinProcess("sim_devices.ur:standalone_host",
                          {"host": free_address(), "time_scale": 1.0, "seed": 5, "trajectory_dir": str(directory),
                           **QUIET})
    process.start()
    process.trajectories = directory
    yield process
    process.stop()


@pytest.fixture(scope="module")
def robot(twin):
    device = create({"adapter": "ur_rtde", "host": twin.endpoints["host"], "connect_timeout": 3.0,
                     "move_timeout": 20.0}, name="robot", envelope=ENVELOPE)
    device.open()
    device.set_tcp(TCP)
    yield device
    device.close()


def last_record(twin, closed: bool = True, timeout: float = 6.0) -> Trajectory:
    """The newest trajectory record (waiting until it is closed: its ring-down has died out)."""
    log = TrajectoryLog(twin.trajectories)
    deadline = time.monotonic() + timeout
    while True:
        records = log.records()
        if records and (records[-1].closed or not closed):
            return records[-1]
        assert time.monotonic() < deadline, "the move's trajectory record did not close"
        time.sleep(0.05)


def test_move_path_rounds_the_corner_by_the_blend_and_reports_done(twin, robot):
    robot.move_linear(REFERENCE)
    corner = REFERENCE + [0.06, 0.0, 0.0, 0.0, 0.0, 0.0]
    end = corner + [0.0, 0.05, 0.0, 0.0, 0.0, 0.0]
    blend = 0.012
    robot.move_path(np.array([corner, end]), speed=0.1, acceleration=1.0, blend_radius=[blend, 0.0])
    done = robot.last_move_done_time()
    np.testing.assert_allclose(robot.tcp_pose()[:3], end[:3], atol=1e-7)  # the controller reports the end
    record = last_record(twin)
    assert record.meta["kind"] == "path"
    commanded = record.commanded_tcp()[:, :3, 3]
    true = record.true_tcp()[:, :3, 3]
    expected = 0.5 * blend * math.sin(math.pi / 4)  # a 90° corner: the blend's vertex
    assert np.min(np.linalg.norm(commanded - corner[:3], axis=1)) == pytest.approx(expected, rel=0.01)
    # The true tool rounds it alike (lag and sag of a few µm at 0.1 m/s), and never stops at the corner.
    assert np.min(np.linalg.norm(true - corner[:3], axis=1)) == pytest.approx(expected, abs=20e-6)
    speed = np.linalg.norm(np.diff(commanded, axis=0), axis=1) / np.diff(record.time)
    near = np.linalg.norm(commanded[1:] - corner[:3], axis=1) < blend
    assert np.min(speed[near]) > 0.5 * np.max(speed)
    # Done once the encoders settled: its controller time is the record's (see _DONE_LATE_BY).
    assert done is not None and -0.01 <= done - record.meta["done_timestamp"] <= _DONE_LATE_BY
    assert record.meta["profile_end"] <= done


def test_move_path_refuses_overlapping_blends_before_sending(twin, robot):
    robot.move_linear(REFERENCE)
    events = len(twin.call("events"))
    corner = REFERENCE + [0.02, 0.0, 0.0, 0.0, 0.0, 0.0]
    with pytest.raises(MotionRefused, match="overlaps its neighbours"):
        robot.move_path(np.array([corner, corner + [0, 0.05, 0, 0, 0, 0]]), blend_radius=0.015)
    with pytest.raises(MotionRefused, match=r"\(n, 6\)"):
        robot.move_path(np.zeros((2, 5)))
    with pytest.raises(MotionRefused, match="one line"):
        robot.move_circular(REFERENCE + [0.01, 0, 0, 0, 0, 0], REFERENCE + [0.02, 0, 0, 0, 0, 0])
    assert len(twin.call("events")) == events


def test_move_circular_keeps_the_true_tool_on_the_circle(twin, robot):
    radius = 0.03
    centre = REFERENCE + [0.05, 0.0, 0.0, 0.0, 0.0, 0.0]
    start, far = centre - [radius, 0, 0, 0, 0, 0], centre + [radius, 0, 0, 0, 0, 0]
    via_1, via_2 = centre + [0, radius, 0, 0, 0, 0], centre - [0, radius, 0, 0, 0, 0]
    robot.move_linear(start)
    time.sleep(0.5)  # that move's ring-down dies out (its record ends when the next move starts)
    robot.move_circular(np.array([via_1, via_2]), np.array([far, start]), speed=0.08, acceleration=1.0,
                        blend_radius=0.001)
    done = robot.last_move_done_time()
    np.testing.assert_allclose(robot.tcp_pose()[:3], start[:3], atol=1e-7)  # a full circle: back at the start
    record = last_record(twin)
    commanded = record.commanded_tcp()[:, :3, 3]
    true = record.true_tcp()[:, :3, 3]
    r_commanded = np.linalg.norm(commanded - centre[:3], axis=1)
    np.testing.assert_allclose(r_commanded, radius, atol=1e-9)
    # The true tool follows within micrometres: while cruising it runs ≈ 4 µm outside the commanded
    # circle at 0.08 m/s (the joint servos' following error and the structure's lag on a curve); where
    # the acceleration changes (start, blend, stop) the servos ring a few µm more, also out of the plane.
    speed = np.linalg.norm(np.diff(commanded, axis=0), axis=1) / np.diff(record.time)
    cruising = np.r_[False, np.abs(speed - 0.08) < 1e-3]
    assert np.sum(cruising) > 1000
    off = np.linalg.norm(true - centre[:3], axis=1) - radius
    assert np.max(np.abs(off[cruising])) < 6e-6 and np.max(np.abs(true[cruising, 2] - centre[2])) < 2e-6
    assert np.max(np.abs(off)) < 15e-6 and np.max(np.abs(true[:, 2] - centre[2])) < 15e-6
    # Both half circles are travelled: the angle about the centre sweeps a full turn.
    angle = np.unwrap(np.arctan2(commanded[:, 1] - centre[1], commanded[:, 0] - centre[0]))
    assert np.ptp(angle) == pytest.approx(2 * np.pi, abs=1e-3)
    assert done is not None and -0.01 <= done - record.meta["done_timestamp"] <= _DONE_LATE_BY


def test_done_and_is_steady_come_before_the_true_tool_has_settled(twin, robot):
    robot.move_linear(REFERENCE)
    t_before = robot.controller_time()
    robot.move_linear(REFERENCE + [0.08, 0.0, 0.0, 0.0, 0.0, 0.0], speed=0.8, acceleration=2.5)
    done = robot.last_move_done_time()
    deadline = time.monotonic() + 2.0
    while not robot.is_steady():  # the controller's view: its encoders at rest for a few cycles
        assert time.monotonic() < deadline
        time.sleep(0.005)
    steady = robot.controller_time()
    assert t_before < done < steady
    record = last_record(twin)
    true = record.true_tcp()[:, :3, 3]
    distance = np.linalg.norm(true - true[-1], axis=1)
    # The controller's signal follows its encoders: the first package at rest ("end_timestamp") comes
    # once the servos settled, and "done" right after it (later only if this host is slow) ...
    assert record.meta["profile_end"] < record.meta["servo_settled"] <= record.meta["end_timestamp"] <= done
    # ... while the true tool still rings after it, micrometres about its attained pose ...
    after = (record.time >= record.meta["end_timestamp"]) & (record.time < record.meta["end_timestamp"] + 0.1)
    assert np.max(distance[after]) > 2e-6
    # ... and settles onto it later, within the structure's decay (ζω ≈ 20/s: 0.5 s ≫ 1/20 s).
    later = record.time > record.meta["end_timestamp"] + 0.5
    assert np.any(later) and np.max(distance[later]) < 0.2e-6


def test_a_stalled_controller_fails_the_new_commands_typed_and_in_time(twin, robot):
    """The twin stops streaming for 3 s: each new command raises a typed error naming the robot and
    the operation, well before its move timeout, and the robot works again after a fresh open."""
    robot.move_linear(REFERENCE)
    corner = REFERENCE + [0.03, 0.0, 0.0, 0.0, 0.0, 0.0]
    twin.call("arm_fault", kind="stall", seconds=3.0)
    t0 = time.monotonic()
    with pytest.raises((DeviceConnectionError, DeviceTimeout)) as caught:
        robot.move_path(np.array([corner, corner + [0, 0.03, 0, 0, 0, 0]]), speed=0.02, blend_radius=0.005)
    assert caught.value.device == "robot" and caught.value.operation == "moveL path"
    assert time.monotonic() - t0 < robot.move_timeout
    with pytest.raises(DeviceConnectionError) as broken:
        robot.controller_time()
    assert broken.value.operation == "read controller time"
    time.sleep(3.0)
    robot.close()
    robot.open()
    robot.move_linear(REFERENCE)
    twin.call("arm_fault", kind="stall", seconds=3.0)
    t0 = time.monotonic()
    with pytest.raises((DeviceConnectionError, DeviceTimeout)) as caught:
        robot.move_circular(REFERENCE + [0.02, 0.02, 0, 0, 0, 0], REFERENCE + [0.04, 0, 0, 0, 0, 0], speed=0.02)
    assert caught.value.device == "robot" and caught.value.operation == "moveC"
    assert time.monotonic() - t0 < robot.move_timeout
    time.sleep(3.0)
    robot.close()
    robot.open()
    robot.move_linear(REFERENCE)
    np.testing.assert_allclose(robot.tcp_pose()[:3], REFERENCE[:3], atol=1e-7)
