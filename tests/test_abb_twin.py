"""The IRC5 twin (``sim_devices.abb``) against ABB's real Python clients in this process: RWS
(``abb_robot_client.rws.RWS``), EGM (``abb_robot_client.egm.EGM``'s own decoder) and
``abb_motion_program_exec``; the twin runs in its own process.

Twins here use <block>.170 … 189 (port 80 and UDP 6510 free there).
"""

from __future__ import annotations

import ast
import itertools
import math
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from sim_devices import TwinProcess
from sim_devices.cell import free_loopback_host

rws_module = pytest.importorskip("abb_robot_client.rws")
egm_module = pytest.importorskip("abb_robot_client.egm")
abb = pytest.importorskip("abb_motion_program_exec")

pytestmark = pytest.mark.timeout(120)
RWS_PORT, EGM_PORT = 80, 6510
TIME_SCALE = 5.0
_addresses = itertools.count(170)
ROOT = Path(__file__).resolve().parents[1]


def free_address() -> str:
    return free_loopback_host(first=next(_addresses), last=189, tcp_ports=(RWS_PORT,), udp_ports=(EGM_PORT,))


@pytest.fixture(scope="module")
def twin():
    process = TwinProcess("sim_devices.abb:standalone_host",
                          {"host": free_address(), "port": RWS_PORT, "time_scale": TIME_SCALE, "seed": 3})
    process.start()
    yield process
    process.stop()


@pytest.fixture(scope="module")
def rws(twin):
    client = rws_module.RWS(twin.endpoints["base_url"])
    yield client
    client.close()


@pytest.fixture(scope="module")
def egm(twin):
    """The client's EGM class on a socket bound to the twin's loopback address (it binds '' itself)."""
    client = egm_module.EGM.__new__(egm_module.EGM)
    client.socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client.socket.bind((twin.endpoints["host"], EGM_PORT))
    client.send_sequence_number, client.egm_addr, client.count = 0, None, 0
    yield client
    client.close()


# ------------------------------------------------------------------------------- independent kinematics
def _revolute(axis, point, angle):
    """The screw motion of a revolute joint: rotation ``angle`` about ``axis`` through ``point``."""
    axis = np.asarray(axis, float)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    r = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = r, (np.eye(3) - r) @ np.asarray(point, float)
    return t


def irb2600_flange(q_deg):
    """tool0 of an IRB 2600-12/1.65 by the product of exponentials, from its published geometry
    (written here, independently of the twin's DH table)."""
    screws = [((0, 0, 1), (0, 0, 0)), ((0, 1, 0), (0.150, 0, 0.445)), ((0, 1, 0), (0.150, 0, 1.145)),
              ((1, 0, 0), (0, 0, 1.260)), ((0, 1, 0), (0.945, 0, 1.260)), ((1, 0, 0), (0, 0, 1.260))]
    home = np.eye(4)
    home[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]  # tool0 z along base x, x pointing down
    home[:3, 3] = (1.030, 0, 1.260)
    t = np.eye(4)
    for (axis, point), angle in zip(screws, np.radians(q_deg)):
        t = t @ _revolute(axis, point, angle)
    return t @ home


def quaternion_matrix(q):
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


# ------------------------------------------------------------------------------- RWS
def test_panel_execution_and_tasks(rws):
    state = rws.get_execution_state()
    assert (state.ctrlexecstate, rws.get_controller_state(), rws.get_operation_mode()) == ("stopped", "motoron",
                                                                                            "AUTO")
    tasks = rws.get_tasks()
    assert tasks["T_ROB1"].motiontask and tasks["T_ROB1"].active and not tasks["logger"].motiontask
    rws.set_speedratio(50)
    assert rws.get_speedratio() == 50
    rws.set_speedratio(100)
    assert rws.get_ramdisk_path() == "$TEMP"
    log = rws.read_event_log()
    assert log[0].seqnum > log[-1].seqnum and {e.code for e in log} >= {10011}  # newest first; motors on


def test_digest_auth_is_required(twin):
    wrong = rws_module.RWS(twin.endpoints["base_url"], "Default User", "wrong password")
    with pytest.raises(Exception, match="HTTP error 401"):
        wrong.get_controller_state()
    import requests  # the challenge itself: Digest, qop auth, the controller's realm

    answer = requests.get(twin.endpoints["base_url"] + "/rw/panel/ctrlstate?json=1", timeout=5)
    assert answer.status_code == 401
    assert answer.headers["WWW-Authenticate"].startswith('Digest realm="validusers@robapi.abb", qop="auth"')


def test_io_signals_and_rapid_data(rws):
    rws.set_digital_io("motion_program_log_motion", 0)
    assert rws.get_digital_io("motion_program_log_motion") == 0
    rws.set_digital_io("motion_program_log_motion", 1)
    rws.set_analog_io("motion_program_preempt_cmd_num", 14.25)
    assert rws.get_analog_io("motion_program_preempt_cmd_num") == pytest.approx(14.25)
    with pytest.raises(rws_module.ABBException):
        rws.get_digital_io("no_such_signal")
    rws.set_rapid_variable_num("opr_counter", 123.456, "T_ROB1/Module1")
    assert rws.get_rapid_variable_num("opr_counter", "T_ROB1/Module1") == pytest.approx(123.456)
    rws.set_rapid_variable("opr_label", '"Hello IRC5"', "T_ROB1")
    assert rws.get_rapid_variable("opr_label", "T_ROB1") == '"Hello IRC5"'
    tool = "[TRUE,[[0,0,80],[1,0,0,0]],[2.5,[0,0,40],[1,0,0,0],0,0,0]]"
    rws.set_rapid_variable("motion_program_tool", tool)
    assert rws.get_rapid_variable("motion_program_tool") == tool
    with pytest.raises(rws_module.ABBException):  # a num is not a tooldata
        rws.set_rapid_variable("motion_program_tool", "5")


def test_file_service(rws):
    ramdisk = rws.get_ramdisk_path()
    data = bytes(range(256)) * 3
    rws.upload_file(f"{ramdisk}/probe.bin", data)
    assert "probe.bin" in rws.list_files(ramdisk)
    assert rws.read_file(f"{ramdisk}/probe.bin") == data
    rws.delete_file(f"{ramdisk}/probe.bin")
    assert "probe.bin" not in rws.list_files(ramdisk)
    with pytest.raises(Exception, match="File not found"):
        rws.read_file(f"{ramdisk}/probe.bin")


def test_robtarget_and_jointtarget_agree_with_the_published_kinematics(rws, twin):
    joints = rws.get_jointtarget().robax
    flange = irb2600_flange(joints)
    target = rws.get_robtarget("ROB_1", "tool0", "wobj0", "Base")
    np.testing.assert_allclose(target.trans * 1e-3, flange[:3, 3], atol=1e-7)
    np.testing.assert_allclose(quaternion_matrix(target.rot), flange[:3, :3], atol=1e-8)
    np.testing.assert_allclose(np.radians(joints), twin.call("state")["arm_actual_q"], atol=1e-9)
    assert target.robconf[0] == math.floor(joints[0] / 90)  # cf1: axis 1's quadrant


# ------------------------------------------------------------------------------- motion programs
def test_a_motion_program_runs_and_its_joint_log_comes_back(rws, twin):
    client = abb.MotionProgramExecClient(abb_client=rws)
    start = rws.get_robtarget()
    conf = abb.confdata(*start.robconf)
    here = np.asarray(start.trans)

    def target(offset_mm):
        return abb.robtarget(list(here + offset_mm), list(start.rot), conf, [9e9] * 6)

    joints = rws.get_jointtarget().robax.copy()
    joints[0] += 5.0
    program = abb.MotionProgram(tool=abb.tooldata(True, abb.pose([0, 0, 0], [1, 0, 0, 0]),
                                                  abb.loaddata(0.5, [0, 0, 20], [1, 0, 0, 0], 0, 0, 0)))
    program.MoveAbsJ(abb.jointtarget(list(rws.get_jointtarget().robax), [9e9] * 6), abb.v500, abb.fine)
    program.MoveJ(target([0, 60, 0]), abb.v500, abb.fine)
    program.MoveL(target([40, 60, -30]), abb.v200, abb.z10)
    program.MoveL(target([40, 0, -30]), abb.v200, abb.fine)
    program.MoveC(target([20, -20, -30]), target([0, 0, -30]), abb.v100, abb.fine)
    program.WaitTime(0.2)
    visits = len(twin.call("visits"))
    log = client.execute_motion_program(program)
    assert log.column_headers == ["timestamp", "cmdnum", "J1", "J2", "J3", "J4", "J5", "J6"]
    stamps, cmdnums = log.data[:, 0], log.data[:, 1]
    np.testing.assert_allclose(np.diff(stamps), 0.004, atol=1e-5)  # the logger's 4 ms
    # -1 until the first move starts (the module's trap sets the number), then every command in order
    order = list(dict.fromkeys(cmdnums.astype(int)))
    assert order[1:] if order[0] == -1 else order == [1, 2, 3, 4, 5, 6]
    end = rws.get_robtarget()
    np.testing.assert_allclose(end.trans, here + [0, 0, -30], atol=1e-4)
    np.testing.assert_allclose(log.data[-1, 2:], rws.get_jointtarget().robax, atol=1e-3)
    # Fine points: MoveAbsJ, MoveJ, the second MoveL (the first was a zone) and the MoveC.
    assert len(twin.call("visits")) - visits == 4
    assert twin.call("truth", event="payload")[-1]["mass"] == pytest.approx(0.5 + 0.001, rel=1e-6)
    names = [entry["title"] for entry in twin.call("elog", count=8)]
    assert names[:3] == ["Motion Program Complete", "Motion Program Log File Closed", "Motion Program Log File Opened"]


def test_an_unreachable_target_is_a_rapid_error_in_the_event_log(rws, twin):
    client = abb.MotionProgramExecClient(abb_client=rws)
    start = rws.get_robtarget()
    program = abb.MotionProgram()
    program.MoveL(abb.robtarget([3000.0, 0.0, 500.0], list(start.rot), abb.confdata(0, 0, 0, 0), [9e9] * 6),
                  abb.v100, abb.fine)
    # Before any move started the module's current command is still -1 (motion_program_init).
    with pytest.raises(Exception, match=r"Motion Program Failed at command number -1 with error code 50050"):
        client.execute_motion_program(program)
    assert rws.get_execution_state().ctrlexecstate == "stopped"
    np.testing.assert_allclose(rws.get_robtarget().trans, start.trans, atol=1e-6)  # nothing moved


def test_a_guard_stop_mid_program_stops_rapid_and_the_panel_says_so(rws, twin):
    client = abb.MotionProgramExecClient(abb_client=rws)
    start = rws.get_robtarget()
    program = abb.MotionProgram()
    program.MoveL(abb.robtarget(list(start.trans + [0, 80, 0]), list(start.rot), abb.confdata(*start.robconf),
                                [9e9] * 6), abb.v100, abb.fine)
    twin.call("arm_fault", kind="protective_stop", at=0.4)
    with pytest.raises(Exception, match="Could not find log file messages"):  # it never finished
        client.execute_motion_program(program)
    assert rws.get_controller_state() == "guardstop"
    with pytest.raises(rws_module.ABBException):  # no motors on while the guard is open
        rws.set_controller_state("motoron")
    twin.call("release_safety")
    assert rws.get_controller_state() == "motoroff"
    rws.set_controller_state("motoron")
    assert rws.get_controller_state() == "motoron"
    moved = float(np.linalg.norm(rws.get_robtarget().trans - start.trans))
    assert 20 < moved < 60  # stopped about 40 % along the 80 mm


# ------------------------------------------------------------------------------- subscriptions
def test_subscription_events_over_the_websocket(rws, twin):
    events: list = []
    arrived = threading.Condition()

    def handler(event):
        with arrived:
            events.append(event)
            arrived.notify_all()

    R = rws_module.SubscriptionResourceRequest
    T, P = rws_module.SubscriptionResourceType, rws_module.SubscriptionResourcePriority
    subscription = rws.subscribe([R(T.ControllerState, P.Medium), R(T.ExecutionState, P.Medium),
                                  R(T.Signal, P.High, "motion_program_preempt"),
                                  R(T.PersVar, P.High, "opr_counter"), R(T.Elog, P.Medium)], handler)
    try:
        deadline = time.monotonic() + 5
        while not twin.call("connections")["subscriptions"] or not any(twin.call("connections")
                                                                         ["subscriptions"].values()):
            assert time.monotonic() < deadline, "the WebSocket did not connect"
            time.sleep(0.02)
        rws.set_analog_io("motion_program_preempt", 3)
        rws.set_rapid_variable_num("opr_counter", 7)
        rws.set_controller_state("motoroff")
        rws.set_controller_state("motoron")

        def seen(kind, **fields):
            return any(isinstance(e, kind) and all(getattr(e, k) == v for k, v in fields.items()) for e in events)

        with arrived:
            assert arrived.wait_for(lambda: seen(rws_module.Signal, name="motion_program_preempt", lvalue="3")
                                    and seen(rws_module.VariableValue, name="T_ROB1", value="7")
                                    and seen(rws_module.ControllerState, state="motoroff")
                                    and seen(rws_module.ControllerState, state="motoron")
                                    and seen(rws_module.EventLogEntryEvent), 5.0), events
    finally:
        subscription.close()


# ------------------------------------------------------------------------------- EGM
def test_egm_feedback_at_250_hz_without_a_missing_sequence_number_for_10_s(egm, rws, twin):
    """While a motion program runs, the feedback follows it and RAPID's state flips; ten seconds of
    packets, every sequence number once, controller time in 4 ms steps (catch-up after a late
    cycle keeps the grid on a loaded machine)."""
    received = []
    t_end = time.monotonic() + 10.0
    client = abb.MotionProgramExecClient(abb_client=rws)
    start = rws.get_robtarget()
    program = abb.MotionProgram()
    program.MoveL(abb.robtarget(list(start.trans + [0, -50, 0]), list(start.rot), abb.confdata(*start.robconf),
                                [9e9] * 6), abb.v100, abb.fine)
    program.MoveL(abb.robtarget(list(start.trans), list(start.rot), abb.confdata(*start.robconf), [9e9] * 6),
                  abb.v100, abb.fine)
    while egm.receive_from_robot(0)[0]:  # what waited in the socket before
        pass
    runner = threading.Thread(target=lambda: (time.sleep(1.0), client.execute_motion_program(program)), daemon=True)
    runner.start()
    while time.monotonic() < t_end:
        ok, state = egm.receive_from_robot(0.5)
        assert ok, "no EGM packet within 0.5 s"
        received.append((state.robot_message.header.seqno, state.robot_message.header.tm, state.rapid_running,
                         state.motors_on, state.joint_angles, state.cartesian[0]))
    runner.join(10)
    seqnos = np.array([r[0] for r in received])
    stamps = np.array([r[1] for r in received])
    assert np.all(np.diff(seqnos) == 1), f"missing sequence numbers: {np.flatnonzero(np.diff(seqnos) != 1)[:5]}"
    assert np.all(np.diff(stamps) == 4)
    assert len(received) >= 0.9 * 2500  # 250 Hz for 10 s
    running = [r[2] for r in received]
    assert any(running) and not running[0] and not running[-1] and all(r[3] for r in received)
    positions = np.array([r[5] for r in received])
    assert np.ptp(positions[:, 1]) == pytest.approx(50.0, abs=0.5)  # the feedback followed the move (mm)
    flange = irb2600_flange(received[-1][4])
    np.testing.assert_allclose(positions[-1] * 1e-3, flange[:3, 3], atol=1e-6)


def test_egm_stall_and_lost_packets(egm, twin):
    ok, state = egm.receive_from_robot(1.0)
    assert ok
    while True:  # the newest packet that waited in the socket
        more, newer = egm.receive_from_robot(0)
        if not more:
            break
        state = newer
    seqnos: list[int] = [state.robot_message.header.seqno]
    twin.call("arm_fault", kind="stall", packets=5)
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and not (len(seqnos) > 1 and np.any(np.diff(seqnos) != 1)):
        ok, state = egm.receive_from_robot(0.5)
        assert ok
        seqnos.append(state.robot_message.header.seqno)
    for _ in range(20):  # and on it goes, every number once
        seqnos.append(egm.receive_from_robot(0.5)[1].robot_message.header.seqno)
    gaps = np.diff(seqnos)
    assert sorted(gaps)[-1] == 6 and np.sum(gaps != 1) == 1  # five numbers skipped, once
    assert twin.call("egm_stats")["lost"] >= 5


def test_rws_503_and_the_twin_never_imports_the_clients(rws, twin):
    twin.call("arm_fault", kind="exception", status=503)
    with pytest.raises(Exception, match="500 Internal Server Error"):  # the client's words for any 503
        rws.get_execution_state()
    assert rws.get_execution_state().ctrlexecstate == "stopped"  # one request only
    # The twin's codec is its own: it never imports the clients' protocol code.
    for path in (ROOT / "sim_devices" / "abb").glob("*.py"):
        tree = ast.parse(path.read_text())
        modules = {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
        modules |= {node.module or "" for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
        assert not {m for m in modules if m.split(".")[0] in ("abb_robot_client", "abb_motion_program_exec",
                                                                "google", "requests", "websocket")}, path
