"""``URRobot`` (drivers.robot, adapter ``ur_rtde``) against the UR twin in its own process.

Twins here use 127.0.0.30 … 127.0.0.49 (test_ur_twin.py uses 10 … 29).
"""

import itertools
import socket
import threading
import time

import numpy as np
import pytest
from scipy import stats

from drivers import DeviceConnectionError, DeviceTimeout, MotionRefused, SettingsError
from drivers.robot import (
    EmergencyStop,
    MotionEnvelope,
    ProtectiveStop,
    Robot,
    RobotIdentity,
    URRobot,
    URRtdeSettings,
    create,
)
from sim_devices import TwinProcess
from sim_devices._transforms import invert, matrix_to_rotvec, pose6_to_matrix
from sim_devices.cell import free_loopback_host

pytest.importorskip("rtde_control")

TIME_SCALE = 20.0
SIGMA_T = 10e-6
SIGMA_R = np.radians(0.001)
TCP = np.array([0.0, 0.0, 0.08, 0.0, 0.0, 0.0])
REFERENCE = np.array([0.45, -0.10, 0.35 - 0.08, np.pi, 0.0, 0.0])  # TCP at the reference flange pose
ENVELOPE = MotionEnvelope.from_dict({"box_min": [0.25, -0.35, 0.10], "box_max": [0.70, 0.25, 0.60],
                                     "max_tilt": 0.6, "max_speed": 0.5, "max_acceleration": 2.0})
_addresses = itertools.count(30)


def free_address() -> str:
    """A loopback address (127.0.0.30-49) not used before in this module whose UR ports are free:
    a client of an earlier test may still be reconnecting to the addresses it used."""
    return free_loopback_host(first=next(_addresses), last=49)


@pytest.fixture(scope="module")
def twin():
    process = TwinProcess("sim_devices.ur:standalone_host",
                          {"host": free_address(), "time_scale": TIME_SCALE, "seed": 7,
                           "repeatability_translation_std": SIGMA_T, "repeatability_rotation_std": SIGMA_R,
                           "thermal_drift_amplitude": 0.0})
    process.start()
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


def test_factory_builds_a_robot_and_rejects_bad_config():
    robot = create({"adapter": "ur_rtde", "host": "127.0.0.99"}, name="arm", envelope=ENVELOPE)
    assert isinstance(robot, URRobot) and isinstance(robot, Robot) and robot.name == "arm"
    assert robot.envelope is ENVELOPE and robot.host == "127.0.0.99"
    assert create(URRtdeSettings(host="127.0.0.98"), name="arm", envelope=ENVELOPE).host == "127.0.0.98"
    with pytest.raises(SettingsError, match=r"^robot 'arm': unknown adapter 'kuka'; expected one of ur_rtde, abb_rws$"):
        create({"adapter": "kuka"}, name="arm", envelope=ENVELOPE)
    with pytest.raises(SettingsError, match=r"^robot 'arm' \(ur_rtde\): unknown setting 'hots'; expected one of host"):
        create({"adapter": "ur_rtde", "hots": "127.0.0.2"}, name="arm", envelope=ENVELOPE)
    # The envelope is the station's, never a robot setting.
    with pytest.raises(SettingsError, match="unknown setting 'envelope'"):
        create({"adapter": "ur_rtde", "envelope": {}}, name="arm", envelope=ENVELOPE)
    with pytest.raises(SettingsError, match=r"frequency: input should be greater than 0 \(got -1\)"):
        create({"adapter": "ur_rtde", "frequency": -1}, name="arm", envelope=ENVELOPE)


def test_envelope_refuses_before_anything_is_sent(twin, robot):
    events = len(twin.call("events"))
    outside = REFERENCE + [0.0, 0.0, 0.5, 0.0, 0.0, 0.0]
    with pytest.raises(MotionRefused, match="z = "):
        robot.move_linear(outside)
    with pytest.raises(MotionRefused, match="speed"):
        robot.move_linear(REFERENCE, speed=0.8)
    with pytest.raises(MotionRefused, match="orientation"):
        robot.move_linear(np.r_[REFERENCE[:3], 0.0, 0.0, 0.0])
    assert len(twin.call("events")) == events  # the controller saw nothing
    # Even with no connection at all, the refusal comes first (no I/O involved).
    offline = URRobot(URRtdeSettings(host="127.0.0.99"), name="offline", envelope=ENVELOPE)
    with pytest.raises(MotionRefused):
        offline.move_linear(outside)


def test_pose_readback_and_tcp(robot):
    np.testing.assert_allclose(robot.tcp_offset(), TCP)
    robot.move_linear(REFERENCE)
    pose = robot.tcp_pose()
    np.testing.assert_allclose(pose[:3], REFERENCE[:3], atol=1e-9)
    assert robot.joint_positions().shape == (6,)
    state = robot.state()
    assert state.connected and state.program_running and not state.protective_stop


def test_move_linear_and_move_joint_blocking_and_async(robot):
    target = REFERENCE + [0.05, 0.02, -0.03, 0.0, 0.0, 0.0]
    robot.move_linear(target)
    np.testing.assert_allclose(robot.tcp_pose()[:3], target[:3], atol=1e-7)
    q = robot.joint_positions() + [0.05, 0.0, 0.0, 0.0, 0.0, 0.1]
    robot.move_joint(q)
    np.testing.assert_allclose(robot.joint_positions(), q, atol=1e-9)
    robot.move_linear(REFERENCE, asynchronous=True)
    robot.wait_until_steady(timeout=10.0)
    deadline = time.monotonic() + 10
    while not np.allclose(robot.tcp_pose()[:3], REFERENCE[:3], atol=1e-7):
        assert time.monotonic() < deadline
        time.sleep(0.005)
    with pytest.raises(MotionRefused):
        robot.move_joint(q, speed=5.0)


def test_stop_mid_move(twin, robot):
    robot.move_linear(REFERENCE)
    # 20 s simulated (1 s of wall time at ×20): long enough to be caught mid-move on a loaded machine.
    robot.move_linear(REFERENCE + [0, 0, 0.2, 0, 0, 0], speed=0.01, acceleration=0.5, asynchronous=True)
    deadline = time.monotonic() + 5
    while robot.tcp_pose()[2] < REFERENCE[2] + 0.005:  # stop it early on
        assert time.monotonic() < deadline
        time.sleep(0.002)
    robot.stop(2.0)
    robot.wait_until_steady(5.0)
    z = robot.tcp_pose()[2]
    assert REFERENCE[2] + 0.005 < z < REFERENCE[2] + 0.19
    assert twin.call("visits")[-1]["stopped"]


def test_iso_repeatability_of_30_visits_matches_the_configured_sigma(twin, robot):
    """30 visits to one pose from the same approach side; the world's true attained TCP poses
    must scatter with the configured σ (pooled over x, y, z: 3·29 degrees of freedom)."""
    pose = REFERENCE + [0.02, 0.03, 0.0, 0.0, 0.0, 0.0]
    approach = pose + [0.0, 0.0, 0.03, 0.0, 0.0, 0.0]
    robot.move_linear(approach)
    start = len(twin.call("truth"))
    for _ in range(30):
        robot.move_linear(pose)
        robot.move_linear(approach)
    truth = twin.call("truth")[start:]
    flanges = [np.array(e["flange_pose"]) for e in truth if e["source"] == "robot"][0::2]  # visits to `pose`
    assert len(flanges) == 30
    tcp = [pose6_to_matrix(f) @ pose6_to_matrix(TCP) for f in flanges]
    positions = np.array([t[:3, 3] for t in tcp])
    residual = positions - positions.mean(axis=0)
    dof = 3 * 29
    variance = np.sum(residual**2) / dof
    low, high = stats.chi2.ppf([0.0005, 0.9995], dof) / dof  # 99.9 % interval of s²/σ²
    assert low < variance / SIGMA_T**2 < high
    # ISO 9283 RP = l̄ + 3 S_l; for an isotropic normal error E[RP] ≈ (2√(2/π) + 3√(3 − 8/π)) σ ≈ 3.62 σ.
    distances = np.linalg.norm(residual, axis=1)
    rp = distances.mean() + 3 * distances.std(ddof=1)
    assert 0.6 * 3.62 * SIGMA_T < rp < 1.4 * 3.62 * SIGMA_T
    # Orientation scatter: rotation vectors of R_i R_mean^T, pooled.
    mean_rotation = tcp[0][:3, :3]
    angles = np.array([matrix_to_rotvec(t[:3, :3] @ mean_rotation.T) for t in tcp])
    rot_var = np.sum((angles - angles.mean(axis=0)) ** 2) / dof
    assert low < rot_var / SIGMA_R**2 < high
    # The controller's own readback does not see the error (encoders): it reports the target.
    np.testing.assert_allclose(invert(pose6_to_matrix(robot.tcp_pose())) @ pose6_to_matrix(approach), np.eye(4),
                               atol=1e-7)


def dashboard_answer(host: str, command: str) -> str:
    """The controller's own answer to a dashboard command (plain socket: the truth for the adapter)."""
    with socket.create_connection((host, 29999), timeout=5.0) as sock:
        reader = sock.makefile("rb")
        reader.readline()  # greeting
        sock.sendall(command.encode() + b"\n")
        return reader.readline().decode().strip()


def test_identity_is_read_from_the_controller(twin, robot):
    model = dashboard_answer(twin.endpoints["host"], "get robot model")
    config = twin.call("describe")["config"]
    assert robot.identity() == RobotIdentity(
        manufacturer="Universal Robots",  # from the dashboard's greeting
        model=model,
        serial_number=config["serial_number"],
        controller_version=".".join(str(v) for v in config["version"]),
    )


def test_set_payload_is_set_on_the_controller_and_read_back(twin, robot):
    """``set_payload`` returns only once the controller's RTDE payload outputs report the new values."""
    robot.set_payload(1.25, [0.004, -0.002, 0.035])
    state = twin.call("state")
    assert state["payload"] == pytest.approx(1.25)
    assert state["payload_cog"] == pytest.approx([0.004, -0.002, 0.035], abs=1e-9)
    robot.set_payload(0.8, [0.0, 0.0, 0.0])  # a zero centre of gravity is set too (not "keep the current one")
    state = twin.call("state")
    assert state["payload"] == pytest.approx(0.8) and state["payload_cog"] == pytest.approx([0, 0, 0], abs=1e-8)


def test_set_payload_refuses_bad_values_before_sending(twin, robot):
    events = len(twin.call("events"))
    with pytest.raises(ValueError, match=r"^robot: payload mass must be a finite number >= 0 kg, got nan$"):
        robot.set_payload(float("nan"), [0, 0, 0])
    with pytest.raises(ValueError, match="centre of gravity must be 3 finite numbers"):
        robot.set_payload(1.0, [0.0, 0.1])
    assert len(twin.call("events")) == events


def test_protective_stop_mid_move_raises_and_can_be_recovered(twin, robot):
    robot.move_linear(REFERENCE)
    twin.call("arm_fault", kind="protective_stop", at=0.4)
    with pytest.raises(ProtectiveStop, match="protective stop"):
        robot.move_linear(REFERENCE + [0.1, 0, 0, 0, 0, 0])
    assert robot.state().protective_stop
    with pytest.raises(ProtectiveStop):
        robot.move_linear(REFERENCE)  # refused while stopped, nothing sent
    robot.unlock_protective_stop()
    robot.move_linear(REFERENCE)  # re-uploads the control script, then moves
    np.testing.assert_allclose(robot.tcp_pose()[:3], REFERENCE[:3], atol=1e-7)


def test_emergency_stop_mid_move_raises(twin, robot):
    twin.call("arm_fault", kind="emergency_stop", at=0.3)
    with pytest.raises(EmergencyStop):
        robot.move_linear(REFERENCE + [0, 0.1, 0, 0, 0, 0])
    assert robot.state().emergency_stop
    twin.call("clear_faults")


def test_connection_drop_mid_move_raises_a_connection_error():
    # Its own twin: the module's robot holds the other twin's input registers (a second control
    # connection would be answered IN_USE, as by a real controller).
    twin = TwinProcess("sim_devices.ur:standalone_host", {"host": free_address(), "time_scale": TIME_SCALE})
    twin.start()
    robot = URRobot(URRtdeSettings(host=twin.endpoints["host"], move_timeout=20.0), envelope=ENVELOPE)
    try:
        robot.open()
        robot.set_tcp(TCP)
        robot.move_linear(REFERENCE)
        twin.call("arm_fault", kind="disconnect", at=0.3)
        with pytest.raises(DeviceConnectionError):
            robot.move_linear(REFERENCE + [0.1, 0, 0, 0, 0, 0])
        with pytest.raises(DeviceConnectionError):
            robot.tcp_pose()
        assert not robot.state().connected
    finally:
        twin.stop()  # first: the broken client's own reconnect loop then gives up
        robot.close()


def test_open_times_out_on_a_silent_server():
    """A server that accepts TCP but never answers must give DeviceTimeout, not a hang."""
    host = free_address()
    listeners, accepted = [], []
    for port in (29999, 30004, 30003):
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(4)
        listeners.append(sock)
    stop = threading.Event()

    def accept_forever(sock):
        sock.settimeout(0.1)
        while not stop.is_set():
            try:
                accepted.append(sock.accept()[0])
            except OSError:
                pass

    threads = [threading.Thread(target=accept_forever, args=(s,), daemon=True) for s in listeners]
    for t in threads:
        t.start()
    try:
        robot = URRobot(URRtdeSettings(host=host, connect_timeout=0.5), envelope=MotionEnvelope())
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match="did not answer"):
            robot.open()
        assert time.monotonic() - t0 < 3.0
    finally:
        stop.set()
        for t in threads:
            t.join(1.0)
        for s in listeners + accepted:
            s.close()


def test_open_to_nothing_is_a_connection_error():
    with pytest.raises(DeviceConnectionError, match="cannot reach"):
        URRobot(URRtdeSettings(host=free_address(), connect_timeout=0.5), envelope=MotionEnvelope()).open()
