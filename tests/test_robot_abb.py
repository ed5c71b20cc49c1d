"""``ABBRobot`` (drivers.robot, adapter ``abb_rws``) through the real abb_robot_client and
abb_motion_program_exec clients against the IRC5 twin in its own process, checked on the twin's
ground truth (its attained poses, trajectory records, event log and fault records).

Twins here use <block>.190 … 209 (port 80 and UDP 6510 free there).
"""

from __future__ import annotations

import itertools
import math
import time

import numpy as np
import pytest
from scipy import stats

from drivers import DeviceConnectionError, DeviceTimeout, MotionRefused, SettingsError
from drivers.robot import (
    ABBRobot,
    ABBRwsSettings,
    EmergencyStop,
    MotionEnvelope,
    MotorsOff,
    ProtectiveStop,
    RapidExecutionError,
    Robot,
    RobotIdentity,
    create,
)
from sim_devices import TwinProcess
from sim_devices._transforms import pose6_to_matrix
from sim_devices.cell import free_loopback_host
from sim_devices.trajectory import Trajectory, TrajectoryLog

pytest.importorskip("abb_robot_client")
pytest.importorskip("abb_motion_program_exec")

pytestmark = pytest.mark.timeout(150)
TIME_SCALE = 10.0
SIGMA_T, SIGMA_R = 10e-6, np.radians(0.001)
TCP = np.array([0.0, 0.0, 0.08, 0.0, 0.0, 0.0])
REFERENCE = np.array([0.95, 0.0, 0.90 - 0.08, np.pi, 0.0, 0.0])  # the TCP at the twin's start flange pose
ENVELOPE = MotionEnvelope.from_dict({"box_min": [0.6, -0.4, 0.5], "box_max": [1.3, 0.4, 1.2], "max_tilt": 0.6,
                                     "max_speed": 1.0, "max_acceleration": 3.0})
_addresses = itertools.count(190)


def free_address() -> str:
    return free_loopback_host(first=next(_addresses), last=209, tcp_ports=(80,), udp_ports=(6510,))


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    directory = tmp_path_factory.mktemp("abb") / "trajectories"
    process = TwinProcess("sim_devices.abb:standalone_host",
                          {"host": free_address(), "time_scale": TIME_SCALE, "seed": 11, "truth_rate": 500.0,
                           "trajectory_dir": str(directory), "repeatability_translation_std": SIGMA_T,
                           "repeatability_rotation_std": SIGMA_R, "thermal_drift_amplitude": 0.0})
    process.start()
    process.trajectories = directory
    yield process
    process.stop()


def settings_for(twin, **overrides) -> dict:
    # One adapter at a time: each binds the EGM port. Short bounds, so the fault tests stay short.
    return {"adapter": "abb_rws", "base_url": twin.endpoints["base_url"], "connect_timeout": 5.0,
            "command_timeout": 3.0, "stale_timeout": 1.0, "move_timeout": 30.0, **overrides}


@pytest.fixture(scope="module")
def robot(twin):
    device = create(settings_for(twin), name="robot", envelope=ENVELOPE)
    device.open()
    device.set_tcp(TCP)
    yield device
    device.close()


@pytest.fixture
def clean(twin, robot):
    """Every fault test starts and ends with a healthy controller at the reference pose."""
    twin.call("clear_faults")
    yield
    twin.call("clear_faults")
    robot.move_linear(REFERENCE)


def last_record(twin, timeout: float = 10.0) -> Trajectory:
    log = TrajectoryLog(twin.trajectories)
    deadline = time.monotonic() + timeout
    while True:
        records = log.records()
        if records and records[-1].closed:
            return records[-1]
        assert time.monotonic() < deadline, "the move's trajectory record did not close"
        time.sleep(0.05)


# ------------------------------------------------------------------------------- settings and refusals
def test_factory_builds_the_adapter_and_checks_its_settings():
    device = create({"adapter": "abb_rws", "base_url": "http://127.0.0.99"}, name="arm", envelope=ENVELOPE)
    assert isinstance(device, ABBRobot) and isinstance(device, Robot) and device.base_url == "http://127.0.0.99"
    assert isinstance(create(ABBRwsSettings(), envelope=ENVELOPE), ABBRobot)
    with pytest.raises(SettingsError, match=r"robot 'arm' \(abb_rws\): unknown setting 'base_ulr'"):
        create({"adapter": "abb_rws", "base_ulr": "http://x"}, name="arm", envelope=ENVELOPE)
    with pytest.raises(SettingsError, match="base_url must be http://host"):
        create({"adapter": "abb_rws", "base_url": "ftp://x"}, name="arm", envelope=ENVELOPE)
    # The EGM socket binds loopback unless a user says otherwise.
    with pytest.raises(SettingsError, match="egm_host '192.168.125.5' is not a loopback address"):
        create({"adapter": "abb_rws", "egm_host": "192.168.125.5"}, name="arm", envelope=ENVELOPE)
    assert create({"adapter": "abb_rws", "egm_host": "192.168.125.5", "egm_remote": True},
                  envelope=ENVELOPE).settings.egm_remote


def test_the_envelope_refuses_before_anything_is_sent(twin, robot):
    requests = twin.call("connections")["requests"]
    with pytest.raises(MotionRefused, match="z = "):
        robot.move_linear(REFERENCE + [0.0, 0.0, 0.5, 0.0, 0.0, 0.0])
    with pytest.raises(MotionRefused, match="speed"):
        robot.move_linear(REFERENCE, speed=1.5)
    with pytest.raises(MotionRefused, match="orientation"):
        robot.move_linear(np.r_[REFERENCE[:3], 0.0, 0.0, 0.0])
    with pytest.raises(MotionRefused, match="no forward kinematics"):
        robot.move_joint(np.zeros(6))
    assert twin.call("connections")["requests"] == requests  # the controller saw nothing
    offline = ABBRobot(ABBRwsSettings(base_url="http://127.0.0.99"), name="offline", envelope=ENVELOPE)
    with pytest.raises(MotionRefused):
        offline.move_linear(REFERENCE + [0.0, 0.0, 0.5, 0.0, 0.0, 0.0])


# ------------------------------------------------------------------------------- readback
def test_identity_state_and_readback_come_from_the_controller(twin, robot):
    config = twin.call("describe")["config"]
    assert robot.identity() == RobotIdentity("ABB", config["robot_type"], config["controller_id"],
                                             config["rw_version_name"])
    robot.move_linear(REFERENCE)
    state = robot.state()
    assert state.connected and not state.protective_stop and not state.program_running and state.robot_mode == 2
    np.testing.assert_allclose(robot.tcp_pose(), REFERENCE, atol=1e-7)
    np.testing.assert_allclose(robot.joint_positions(), twin.call("state")["arm_actual_q"], atol=1e-8)
    before = robot.controller_time()
    time.sleep(0.05)
    assert robot.controller_time() > before and robot.is_steady()
    np.testing.assert_allclose(robot.tcp_offset(), TCP, atol=1e-9)


def test_set_payload_is_the_tools_load_on_the_controller(twin, robot):
    robot.set_payload(4.5, [0.0, 0.01, 0.06])
    robot.move_linear(REFERENCE + [0.0, 0.0, 0.01, 0.0, 0.0, 0.0])  # the program carries the tool: SetSysData
    robot.move_linear(REFERENCE)
    payload = twin.call("truth", event="payload")[-1]
    assert payload["mass"] == pytest.approx(4.5 + 0.001, rel=1e-6)  # tool load + the programs' 1 g grip load
    np.testing.assert_allclose(payload["cog"], [0.0, 0.01 * 4.5 / 4.501, (0.06 * 4.5 + 1e-6) / 4.501], atol=1e-6)
    with pytest.raises(ValueError, match="finite"):
        robot.set_payload(float("nan"), [0, 0, 0])
    robot.set_payload(0.0, [0.0, 0.0, 0.0])


# ------------------------------------------------------------------------------- motion
def test_a_blocking_move_reports_its_done_time_and_reaches_its_target(twin, robot):
    robot.move_linear(REFERENCE)
    target = REFERENCE + [0.04, -0.03, 0.02, 0.0, 0.0, 0.0]
    robot.move_linear(target, speed=0.3)
    np.testing.assert_allclose(robot.tcp_pose(), target, atol=1e-7)
    visit = twin.call("visits")[-1]
    done = robot.last_move_done_time()
    # The first EGM packet with RAPID stopped: the core's "done" to a few cycles (a late cycle thread
    # makes up its slots with the state of now; a loaded host delays the twin's RAPID thread more).
    assert done is not None and done == pytest.approx(visit["done_timestamp"], abs=0.15)
    assert robot.controller_time() >= done
    np.testing.assert_allclose(visit["commanded_tcp"], target, atol=1e-9)


def test_an_asynchronous_move_can_be_stopped(twin, robot):
    robot.move_linear(REFERENCE)
    far = REFERENCE + [0.0, 0.2, 0.0, 0.0, 0.0, 0.0]
    robot.move_linear(far, speed=0.05, asynchronous=True)
    deadline = time.monotonic() + 10
    while twin.call("state")["execution"] != "running" or not twin.call("state")["arm_moving"]:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    time.sleep(0.3)
    robot.stop()
    robot.wait_until_steady(timeout=10.0)
    travelled = float(np.linalg.norm(robot.tcp_pose()[:3] - REFERENCE[:3]))
    assert 0.001 < travelled < 0.19  # stopped on the way
    assert twin.call("visits")[-1]["stopped"]


def test_iso_repeatability_of_30_visits_matches_the_configured_sigma(twin, robot):
    """30 visits to one pose from the same side; the world's true attained TCP poses scatter with
    the configured σ (pooled over x, y, z: 3·29 degrees of freedom), RP ≈ 3.62 σ."""
    pose = REFERENCE + [0.02, 0.03, 0.0, 0.0, 0.0, 0.0]
    approach = pose + [0.0, 0.0, 0.02, 0.0, 0.0, 0.0]
    robot.move_linear(approach)
    start = len(twin.call("truth"))
    for _ in range(30):
        robot.move_linear(pose, speed=0.5)
        robot.move_linear(approach, speed=0.5)
    truth = twin.call("truth")[start:]
    flanges = [np.array(e["flange_pose"]) for e in truth if e["source"] == "robot"][0::2]
    assert len(flanges) == 30
    tcp = [pose6_to_matrix(f) @ pose6_to_matrix(TCP) for f in flanges]
    positions = np.array([t[:3, 3] for t in tcp])
    residual = positions - positions.mean(axis=0)
    dof = 3 * 29
    low, high = stats.chi2.ppf([0.0005, 0.9995], dof) / dof
    assert low < np.sum(residual**2) / dof / SIGMA_T**2 < high
    distances = np.linalg.norm(residual, axis=1)
    rp = distances.mean() + 3 * distances.std(ddof=1)
    assert 0.6 * 3.62 * SIGMA_T < rp < 1.4 * 3.62 * SIGMA_T
    np.testing.assert_allclose(robot.tcp_pose(), approach, atol=1e-7)  # the encoders do not see the error


def test_move_path_rounds_the_corner_with_the_zone(twin, robot):
    robot.move_linear(REFERENCE)
    corner = REFERENCE + [0.06, 0.0, 0.0, 0.0, 0.0, 0.0]
    end = corner + [0.0, 0.05, 0.0, 0.0, 0.0, 0.0]
    blend = 0.012
    robot.move_path(np.array([corner, end]), speed=0.1, acceleration=1.0, blend_radius=[blend, 0.0])
    np.testing.assert_allclose(robot.tcp_pose(), end, atol=1e-7)
    record = last_record(twin)
    assert record.meta["kind"] == "path"
    commanded = record.commanded_tcp()[:, :3, 3]
    expected = 0.5 * blend * math.sin(math.pi / 4)  # a 90° corner passed at the blend's vertex
    assert np.min(np.linalg.norm(commanded - corner[:3], axis=1)) == pytest.approx(expected, rel=0.02)
    speed = np.linalg.norm(np.diff(commanded, axis=0), axis=1) / np.diff(record.time)
    near = np.linalg.norm(commanded[1:] - corner[:3], axis=1) < blend
    assert np.min(speed[near]) > 0.5 * np.max(speed)  # never stopped at the corner
    # the first EGM packet after RAPID stopped: one 4 ms packet after the twin says done, later when a
    # loaded host delays the twin's RAPID thread (never the previous move's or a later one's, seconds apart)
    assert robot.last_move_done_time() == pytest.approx(record.meta["done_timestamp"], abs=0.15)
    with pytest.raises(MotionRefused, match="overlaps its neighbours"):
        robot.move_path(np.array([REFERENCE + [0.02, 0, 0, 0, 0, 0], REFERENCE]), blend_radius=[0.015, 0.0])


def test_move_circular_runs_two_arcs_on_one_circle(twin, robot):
    robot.move_linear(REFERENCE)
    radius = 0.03
    centre = REFERENCE[:3] + [radius, 0.0, 0.0]

    def on_circle(angle):
        return np.r_[centre + radius * np.array([-math.cos(angle), math.sin(angle), 0.0]), REFERENCE[3:]]

    robot.move_circular(np.array([on_circle(math.pi / 2), on_circle(3 * math.pi / 2)]),
                        np.array([on_circle(math.pi), on_circle(2 * math.pi)]), speed=0.08, blend_radius=0.005)
    np.testing.assert_allclose(robot.tcp_pose(), REFERENCE, atol=1e-7)
    commanded = last_record(twin).commanded_tcp()[:, :3, 3]
    np.testing.assert_allclose(np.linalg.norm(commanded - centre, axis=1), radius, atol=1e-8)
    assert np.ptp(commanded[:, 0]) == pytest.approx(2 * radius, abs=1e-6)  # all the way round
    with pytest.raises(MotionRefused, match="not on one line"):
        robot.move_circular(REFERENCE + [0.01, 0, 0, 0, 0, 0], REFERENCE + [0.02, 0, 0, 0, 0, 0])


# ------------------------------------------------------------------------------- the fault matrix
def test_a_guard_stop_is_a_protective_stop_then_motors_off_until_switched_on(twin, robot, clean):
    robot.move_linear(REFERENCE)
    twin.call("arm_fault", kind="protective_stop", at=0.5)
    with pytest.raises(ProtectiveStop, match="guard stop"):
        robot.move_linear(REFERENCE + [0.0, 0.08, 0.0, 0.0, 0.0, 0.0], speed=0.2)
    assert robot.state().protective_stop
    with pytest.raises(ProtectiveStop, match="guard stop"):  # nothing moves while the guard is open
        robot.move_linear(REFERENCE)
    twin.call("release_safety")
    with pytest.raises(MotorsOff):
        robot.move_linear(REFERENCE)
    robot.motors_on()
    robot.move_linear(REFERENCE)
    np.testing.assert_allclose(robot.tcp_pose(), REFERENCE, atol=1e-7)


def test_emergency_stop_motors_off_and_a_rapid_error_are_typed(twin, robot, clean):
    target = REFERENCE + [0.0, 0.06, 0.0, 0.0, 0.0, 0.0]
    twin.call("arm_fault", kind="emergency_stop", at=0.5)
    with pytest.raises(EmergencyStop):
        robot.move_linear(target, speed=0.2)
    assert robot.state().emergency_stop
    twin.call("clear_faults")
    robot.move_linear(REFERENCE)
    twin.call("arm_fault", kind="motors_off", at=0.3)
    with pytest.raises(MotorsOff, match="motors are off"):
        robot.move_linear(target, speed=0.2)
    assert isinstance(MotorsOff("r", "o", "c"), ProtectiveStop)  # the engine pauses on it, as on a guard stop
    robot.motors_on()
    robot.move_linear(REFERENCE)
    twin.call("arm_fault", kind="program_stopped", at=0.5, code=41617, title="Too intense frequency")
    with pytest.raises(RapidExecutionError, match="41617"):
        robot.move_linear(target, speed=0.2)
    assert any(e["code"] == 41617 and e["msgtype"] == 3 for e in twin.call("elog", count=10))
    robot.move_linear(REFERENCE)  # RAPID runs again after an execution error


def test_rws_503_and_a_silent_rws_give_typed_errors_in_time(twin, robot, clean):
    twin.call("arm_fault", kind="exception", count=4, status=503, path="/rw/panel/ctrlstate")
    with pytest.raises(DeviceConnectionError, match="503"):  # three tries, then the typed error
        robot.move_linear(REFERENCE)
    twin.call("arm_fault", kind="drop_reply", path="/rw/motionsystem", seconds=6.0)
    started = time.monotonic()
    with pytest.raises(DeviceTimeout, match="did not answer within 3.0 s"):
        robot.tcp_pose()
    assert time.monotonic() - started < 6.0
    robot.move_linear(REFERENCE)  # the next requests are answered again (the fourth 503 retried)


def test_a_lost_egm_stream_during_a_move_stops_it_and_is_a_connection_error(twin, robot, clean):
    robot.move_linear(REFERENCE)
    twin.call("arm_fault", kind="stall", seconds=3.0)
    with pytest.raises(DeviceConnectionError, match="no EGM packet"):
        robot.move_linear(REFERENCE + [0.0, 0.1, 0.0, 0.0, 0.0, 0.0], speed=0.01)  # 2 s of wall time
    deadline = time.monotonic() + 10
    while twin.call("state")["arm_moving"]:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert twin.call("state")["execution"] == "stopped"  # the adapter stopped RAPID: nobody watched the arm
    assert twin.call("visits")[-1]["stopped"]  # on the way, not at the end
    deadline = time.monotonic() + 10
    while True:  # the stream comes back after the stall
        try:
            robot.controller_time()
            break
        except DeviceConnectionError:
            assert time.monotonic() < deadline
            time.sleep(0.1)


def test_close_leaves_no_worker(twin, robot):
    import psutil

    pid = robot.worker_pid
    assert pid is not None and psutil.pid_exists(pid)
    robot.close()
    assert robot.worker_pid is None and not psutil.pid_exists(pid)
    robot.close()  # twice is harmless
    robot.open()  # and it opens again
    assert robot.is_steady() in (True, False)


ENGINE = """
import sys, time
import numpy as np
from drivers.robot import MotionEnvelope, create
envelope = MotionEnvelope.from_dict({"box_min": [0.6, -0.4, 0.5], "box_max": [1.3, 0.4, 1.2], "max_tilt": 0.6})
robot = create({"adapter": "abb_rws", "base_url": sys.argv[1]}, envelope=envelope)
robot.open()
print(robot.worker_pid, flush=True)
robot.move_linear(robot.tcp_pose() + [0.0, 0.15, 0.0, 0.0, 0.0, 0.0], speed=0.01, asynchronous=True)
print("moving", flush=True)
time.sleep(60)
"""


def test_an_engine_killed_mid_move_leaves_the_robot_stopped_and_no_worker(twin, robot):
    """kill -9 of the engine during an asynchronous move: its worker stops RAPID and exits."""
    import os
    import signal
    import subprocess
    import sys

    import psutil

    robot.close()  # one EGM socket per address: the engine below takes it
    engine = subprocess.Popen([sys.executable, "-c", ENGINE, twin.endpoints["base_url"]], stdout=subprocess.PIPE,
                              text=True, cwd=str(__import__("pathlib").Path(__file__).resolve().parents[1]))
    try:
        worker = int(engine.stdout.readline())
        assert engine.stdout.readline().strip() == "moving"
        deadline = time.monotonic() + 10
        while not twin.call("state")["arm_moving"]:
            assert time.monotonic() < deadline
            time.sleep(0.02)
        os.kill(engine.pid, signal.SIGKILL)
        engine.wait(10)
        deadline = time.monotonic() + 15
        while psutil.pid_exists(worker) or twin.call("state")["arm_moving"]:
            assert time.monotonic() < deadline, "the worker outlived its engine or the arm kept moving"
            time.sleep(0.05)
    finally:
        if engine.poll() is None:
            engine.kill()
            engine.wait(10)
    assert twin.call("state")["execution"] == "stopped" and twin.call("visits")[-1]["stopped"]
    robot.open()
    robot.move_linear(REFERENCE)
