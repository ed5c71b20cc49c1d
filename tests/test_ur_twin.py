"""The UR controller twin against the real ur_rtde client (twin in its own process).

Each twin gets its own loopback address (127.0.0.10 … 127.0.0.29 in this module) so tests never
collide with each other or with a cell on 127.0.0.2.
"""

import itertools
import time

import numpy as np
import pytest

from sim_devices import TwinProcess
from sim_devices._transforms import pose6_to_matrix
from sim_devices.cell import free_loopback_host
from sim_devices.ur import _kinematics as kin
from sim_devices.ur._motion import Profile

rtde_control = pytest.importorskip("rtde_control")
rtde_receive = pytest.importorskip("rtde_receive")
dashboard_client = pytest.importorskip("dashboard_client")

TIME_SCALE = 20.0
_addresses = itertools.count(10)


def free_address() -> str:
    """A loopback address (127.0.0.10-29) not used before in this module whose UR ports are free:
    a client of an earlier test may still be reconnecting to the addresses it used."""
    return free_loopback_host(first=next(_addresses), last=29)


def start_twin(**kwargs) -> TwinProcess:
    process = TwinProcess("sim_devices.ur:standalone_host",
                          {"host": free_address(), "time_scale": TIME_SCALE, **kwargs})
    process.start()
    return process


@pytest.fixture(scope="module")
def twin():
    process = start_twin(seed=3)
    yield process
    process.stop()


@pytest.fixture(scope="module")
def clients(twin):
    host = twin.endpoints["host"]
    receive = rtde_receive.RTDEReceiveInterface(host)
    control = rtde_control.RTDEControlInterface(host)
    yield control, receive
    control.disconnect()
    receive.disconnect()


def wait_for(predicate, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.005)


def wait_until_steady(read, interval=0.1, timeout=10.0):
    """The value of ``read()`` once two readings ``interval`` apart are equal."""
    deadline = time.monotonic() + timeout
    last = read()
    while True:
        time.sleep(interval)
        value = read()
        if value == last:
            return value
        assert time.monotonic() < deadline, "value still changing"
        last = value


# ------------------------------------------------------------------------------ pure physics
def test_forward_and_inverse_kinematics_round_trip():
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = kin.HOME_SEED + rng.uniform(-0.4, 0.4, 6)
        tcp = [0.0, 0.01, 0.08, 0.0, 0.0, 0.3]
        pose = kin.forward(q, tcp)
        solved = kin.inverse(pose, q + rng.uniform(-0.05, 0.05, 6), tcp)
        np.testing.assert_allclose(kin.forward(solved, tcp), pose, atol=1e-9)


def test_ur5e_zero_pose_matches_published_dimensions():
    # All joints at zero: the arm lies along -x; flange at x = a2 + a3, y = -(d4 + d6), z = d1 - d5.
    flange = kin.forward(np.zeros(6))
    np.testing.assert_allclose(flange[:3, 3], [-0.425 - 0.3922, -(0.1333 + 0.0996), 0.1625 - 0.0997], atol=1e-12)


def test_trapezoid_covers_its_length_with_its_limits():
    profile = Profile.rest_to_rest(0.0, 0.3, 0.25, 1.2)
    s, v = profile.at(profile.t_end)
    assert s == pytest.approx(0.3) and v == pytest.approx(0.0, abs=1e-12)
    times = np.linspace(0, profile.t_end, 400)
    speeds = np.array([profile.at(t)[1] for t in times])
    assert speeds.max() == pytest.approx(0.25)
    assert np.max(np.abs(np.diff(speeds) / np.diff(times))) <= 1.2 + 1e-6
    # Expected duration: v/a ramps plus the flat part.
    assert profile.t_end == pytest.approx(0.25 / 1.2 + 0.3 / 0.25)


# ------------------------------------------------------------------------------ protocol
def test_connect_reports_the_world_reference_pose(twin, clients):
    control, receive = clients
    assert receive.getSafetyStatusBits() & 1
    assert control.isProgramRunning()
    pose = np.array(receive.getActualTCPPose())
    expected = pose6_to_matrix([0.45, -0.10, 0.35, np.pi, 0.0, 0.0])
    np.testing.assert_allclose(pose6_to_matrix(pose), expected, atol=1e-9)
    np.testing.assert_allclose(kin.forward(receive.getActualQ()), expected, atol=1e-9)


def test_blocking_movel_and_movej_reach_their_targets(twin, clients):
    control, receive = clients
    start = np.array(receive.getActualTCPPose())
    target = start + [0.03, -0.02, 0.04, 0.0, 0.0, 0.0]
    visits = len(twin.call("visits"))
    t0 = time.monotonic()
    assert control.moveL(target.tolist(), 0.25, 1.2)
    elapsed = time.monotonic() - t0
    wait_for(lambda: np.allclose(receive.getActualTCPPose(), target, atol=1e-9))
    # 53.9 mm at 0.25 m/s, 1.2 m/s²: 0.424 s simulated → ≥ 21 ms of wall time at ×20.
    assert elapsed >= 0.424 / TIME_SCALE * 0.9
    new_visits = twin.call("visits", since=visits)
    assert len(new_visits) == 1 and not new_visits[0]["stopped"]
    np.testing.assert_allclose(new_visits[0]["commanded_tcp"], target, atol=1e-9)

    q = np.array(receive.getActualQ())
    q_target = q + [0.05, -0.03, 0.02, 0.0, 0.04, -0.1]
    assert control.moveJ(q_target.tolist(), 1.05, 1.4)
    wait_for(lambda: np.allclose(receive.getActualQ(), q_target, atol=1e-12))
    np.testing.assert_allclose(control.getForwardKinematics(), kin.forward_pose(q_target), atol=1e-9)
    wait_for(control.isSteady)


def test_async_move_progress_and_stopl_mid_move(twin, clients):
    control, receive = clients
    start = np.array(receive.getActualTCPPose())
    target = start + [0.0, 0.0, 0.2, 0.0, 0.0, 0.0]
    assert control.moveL(target.tolist(), 0.02, 0.5, True)  # 10 s simulated, 0.5 s wall
    wait_for(lambda: control.getAsyncOperationProgress() >= 0)  # running
    wait_for(lambda: receive.getActualTCPPose()[2] > start[2] + 0.02)
    control.stopL(2.0)
    wait_for(lambda: control.getAsyncOperationProgress() < 0)
    # The receive stream is a separate connection, which may lag on a loaded machine.
    z_stopped = wait_until_steady(lambda: receive.getActualTCPPose()[2])  # at rest
    assert start[2] + 0.02 < z_stopped < target[2] - 0.01
    assert twin.call("visits")[-1]["stopped"]
    # A full async move: progress turns negative once it is done.
    assert control.moveL(start.tolist(), 0.25, 1.2, True)
    wait_for(lambda: control.getAsyncOperationProgress() < 0)
    wait_for(lambda: np.allclose(receive.getActualTCPPose(), start, atol=1e-9))


def test_tcp_offset_queries_and_pose_trans(twin, clients):
    control, receive = clients
    flange = np.array(receive.getActualTCPPose())
    offset = [0.0, 0.0, 0.08, 0.0, 0.0, 0.0]
    assert control.setTcp(offset)
    np.testing.assert_allclose(control.getTCPOffset(), offset)
    expected = pose6_to_matrix(flange) @ pose6_to_matrix(offset)
    wait_for(lambda: np.allclose(pose6_to_matrix(receive.getActualTCPPose()), expected, atol=1e-9))
    np.testing.assert_allclose(control.poseTrans(flange.tolist(), offset), receive.getActualTCPPose(), atol=1e-9)
    q = control.getInverseKinematics(receive.getActualTCPPose())
    np.testing.assert_allclose(q, receive.getActualQ(), atol=1e-7)
    assert control.setTcp([0.0] * 6)


def test_unknown_command_is_answered_and_logged(twin, clients):
    control, _ = clients
    assert control.zeroFtSensor()  # not emulated: answered 'done', no action
    assert any("not emulated" in e for e in twin.call("events"))


def test_second_control_connection_takes_over_the_running_script(twin, clients):
    control, receive = clients
    host = twin.endpoints["host"]
    # ur_rtde refuses the input registers while another control connection holds them (IN_USE).
    with pytest.raises(RuntimeError, match="in use"):
        rtde_control.RTDEControlInterface(host)
    control.disconnect()  # the script keeps running on the controller
    assert twin.call("state")["runtime_state"] == 2
    second = rtde_control.RTDEControlInterface(host)
    try:
        events = twin.call("events")
        assert any("stop script received" in e for e in events)
        assert second.isProgramRunning()
        start = np.array(receive.getActualTCPPose())
        assert second.moveL((start + [0, 0, 0.01, 0, 0, 0]).tolist(), 0.25, 1.2)
    finally:
        second.disconnect()
    control.reconnect()
    assert control.isProgramRunning()


def test_two_twins_in_parallel_on_their_own_addresses():
    first, second = start_twin(seed=1), start_twin(seed=2)
    try:
        assert first.endpoints["host"] != second.endpoints["host"]
        receivers = [rtde_receive.RTDEReceiveInterface(p.endpoints["host"]) for p in (first, second)]
        controls = [rtde_control.RTDEControlInterface(p.endpoints["host"]) for p in (first, second)]
        start = np.array(receivers[0].getActualTCPPose())
        assert controls[0].moveL((start + [0, 0, 0.05, 0, 0, 0]).tolist(), 0.25, 1.2, True)
        assert controls[1].moveL((start + [0, 0, -0.05, 0, 0, 0]).tolist(), 0.25, 1.2)
        wait_for(lambda: controls[0].getAsyncOperationProgress() < 0)
        wait_for(lambda: abs(receivers[0].getActualTCPPose()[2] - (start[2] + 0.05)) < 1e-9)
        wait_for(lambda: abs(receivers[1].getActualTCPPose()[2] - (start[2] - 0.05)) < 1e-9)
        for client in controls + receivers:
            client.disconnect()
    finally:
        first.stop()
        second.stop()


def test_protective_stop_makes_send_command_fail(twin, clients):
    control, receive = clients
    start = np.array(receive.getActualTCPPose())
    twin.call("arm_fault", kind="protective_stop", at=0.3)
    assert not control.moveL((start + [0, 0, 0.1, 0, 0, 0]).tolist(), 0.25, 1.2)
    # The control client saw the stop; this receive client's stream may lag on a loaded machine.
    wait_for(receive.isProtectiveStopped)
    assert receive.getSafetyMode() == 3
    z = wait_until_steady(lambda: receive.getActualTCPPose()[2])  # after the stop ramp (10 m/s²)
    assert start[2] < z < start[2] + 0.1 - 0.01  # halted mid-move, well short of the target
    dashboard = dashboard_client.DashboardClient(twin.endpoints["host"])
    dashboard.connect()
    assert dashboard.safetystatus() == "Safetystatus: PROTECTIVE_STOP"
    dashboard.unlockProtectiveStop()
    dashboard.disconnect()
    wait_for(lambda: not receive.isProtectiveStopped())
    assert control.reuploadScript()
    wait_for(control.isProgramRunning)
    assert control.moveL(start.tolist(), 0.25, 1.2)


def test_stream_timestamp_advances_while_the_control_thread_is_busy():
    """A real controller keeps streaming its clock; the twin's control thread can be busy for a
    while (publishing a settled pose makes the cell render three frames), and a frozen timestamp
    would make the driver declare the connection lost."""
    import threading

    from sim_devices.faults import FaultPlan
    from sim_devices.ur._config import URTwinConfig
    from sim_devices.ur._controller import URController
    from sim_devices.ur._servers import InputOwnership, RTDEHandler
    from sim_devices.world import World, WorldConfig

    controller = URController(World(WorldConfig(seed=0)), URTwinConfig(time_scale=1.0), FaultPlan())
    timestamp = RTDEHandler(controller, InputOwnership())._getter("timestamp")
    busy, release = threading.Event(), threading.Event()

    def hold_the_controller():
        with controller.lock:
            busy.set()
            release.wait(5.0)

    holder = threading.Thread(target=hold_the_controller)
    holder.start()
    try:
        assert busy.wait(5.0)
        first = timestamp(controller.snapshot)
        time.sleep(0.05)
        assert timestamp(controller.snapshot) >= first + 0.04
    finally:
        release.set()
        holder.join(5.0)


def test_dashboard_answers_like_polyscope():
    from sim_devices.faults import FaultPlan
    from sim_devices.ur._config import URTwinConfig
    from sim_devices.ur._controller import URController
    from sim_devices.ur._servers import DashboardHandler
    from sim_devices.world import World, WorldConfig

    dashboard = DashboardHandler(URController(World(WorldConfig(seed=0)), URTwinConfig(), FaultPlan()))
    expected = {
        "close safety popup": "closing safety popup", "restart safety": "Restarting safety",
        "power on": "Powering on", "power off": "Powering off", "brake release": "Brake releasing",
        "get loaded program": "No program loaded", "isProgramSaved": "false <unnamed>",
        "close popup": "closing popup", "load /programs/x.urp": "File not found: /programs/x.urp",
        "popup hello": "showing popup", "addToLog note": "Added log message",
    }
    for command, reply in expected.items():
        assert dashboard.answer(command) == (reply, False), command
    assert dashboard.answer("quit") == ("Disconnected", True)
