"""``URRobot``'s isolation: the ur_rtde clients in a worker process that can hang or die without
taking the engine along.

Against the real ur_rtde client, the UR twin (its own process) and hostile controllers (plain
sockets in this process: now that the client lives in a worker, a server may share the engine's
process). "Engine" processes are small Python programs started by the tests. Twins and hostile
servers here use 127.0.0.100 … 127.0.0.119.
"""

from __future__ import annotations

import itertools
import os
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import psutil
import pytest

from drivers import DeviceConnectionError, DeviceTimeout
from drivers.robot import MotionEnvelope, URRobot, URRtdeSettings
from sim_devices import TwinProcess
from sim_devices.cell import free_loopback_host

pytest.importorskip("rtde_control")

ROOT = Path(__file__).resolve().parents[1]
TIME_SCALE = 20.0
TCP = [0.0, 0.0, 0.08, 0.0, 0.0, 0.0]
REFERENCE = np.array([0.45, -0.10, 0.35 - 0.08, np.pi, 0.0, 0.0])  # TCP at the twin's reference flange pose
ENVELOPE_DICT = {"box_min": [0.25, -0.35, 0.10], "box_max": [0.70, 0.25, 0.60], "max_tilt": 0.6, "max_speed": 0.5,
                 "max_acceleration": 2.0}
ENVELOPE = MotionEnvelope.from_dict(ENVELOPE_DICT)
_addresses = itertools.count(100)


def free_address() -> str:
    """A loopback address (127.0.0.100-119) not used before in this module whose UR ports are free."""
    return free_loopback_host(first=next(_addresses), last=119)


def workers_of(engine_pid: int) -> list[psutil.Process]:
    """Live ur_rtde worker processes started by ``engine_pid`` (their command line names their parent)."""
    found = []
    for process in psutil.process_iter(["cmdline", "status"]):
        cmdline = process.info["cmdline"] or []
        if (len(cmdline) >= 2 and cmdline[-3:-2] and cmdline[-3].endswith("_ur_worker.py")
                and cmdline[-1] == str(engine_pid) and process.info["status"] != psutil.STATUS_ZOMBIE):
            found.append(process)
    return found


def wait_gone(pid: int, timeout: float) -> bool:
    """True once ``pid`` has exited (a zombie counts as exited), within ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if psutil.Process(pid).status() == psutil.STATUS_ZOMBIE:
                return True
        except psutil.NoSuchProcess:
            return True
        time.sleep(0.05)
    return False


# --------------------------------------------------------------------------------------- fixtures
class HostileController:
    """Listens on the three UR ports of ``host`` and never lets a client finish connecting.

    ``silent``: accepts and never sends a byte. ``after_probe``: sends the dashboard greeting and
    accepts RTDE protocol version 2, as a controller would, then falls silent, so the client's
    constructor waits (holding its process's GIL) for the controller version forever.
    """

    def __init__(self, host: str, mode: str) -> None:
        self.host, self.mode = host, mode
        self.version_requests = 0  # RTDE protocol handshakes answered: the probe's, then the client's
        self._stop = threading.Event()
        self._sockets: list[socket.socket] = []
        self._threads: list[threading.Thread] = []

    def start(self) -> HostileController:
        for port in (29999, 30004, 30003):
            listener = socket.socket()
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            listener.bind((self.host, port))
            listener.listen(8)
            listener.settimeout(0.1)
            self._sockets.append(listener)
            thread = threading.Thread(target=self._accept, args=(listener, port), daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    def _accept(self, listener: socket.socket, port: int) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = listener.accept()
            except OSError:
                continue
            self._sockets.append(conn)
            if self.mode == "after_probe":
                thread = threading.Thread(target=self._half_answer, args=(conn, port), daemon=True)
                thread.start()
                self._threads.append(thread)

    def _half_answer(self, conn: socket.socket, port: int) -> None:
        conn.settimeout(0.1)
        if port == 29999:
            conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
        buffer = b""
        while not self._stop.is_set():
            try:
                chunk = conn.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            if not chunk:
                return
            buffer += chunk
            if port == 30004 and buffer[:3] == struct.pack(">HB", 5, 86):  # protocol version request
                conn.sendall(struct.pack(">HBB", 4, 86, 1))
                buffer = buffer[5:]
                self.version_requests += 1

    def wait_for_client_constructor(self, timeout: float = 20.0) -> None:
        """Until the client's own handshake (after the probe's) was answered: from then on its
        constructor waits for the controller version, holding its process's GIL."""
        deadline = time.monotonic() + timeout
        while self.version_requests < 2:
            assert time.monotonic() < deadline, "the ur_rtde client never reached its constructor"
            time.sleep(0.02)
        time.sleep(0.2)  # the client sends its next request and waits

    def stop(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(2.0)
        for sock in self._sockets:
            sock.close()


@pytest.fixture(params=["silent", "after_probe"])
def hostile(request):
    server = HostileController(free_address(), request.param).start()
    yield server
    server.stop()


@pytest.fixture
def after_probe():
    server = HostileController(free_address(), "after_probe").start()
    yield server
    server.stop()


@pytest.fixture(scope="module")
def twin():
    process = TwinProcess("sim_devices.ur:standalone_host",
                          {"host": free_address(), "time_scale": TIME_SCALE, "seed": 3})
    process.start()
    yield process
    process.stop()


@pytest.fixture
def robot(twin):
    """A robot opened on the twin, closed after the test (a test may kill its worker first)."""
    device = URRobot(URRtdeSettings(host=twin.endpoints["host"], connect_timeout=3.0, command_timeout=3.0,
                                    move_timeout=20.0), name="arm", envelope=ENVELOPE)
    device.open()
    device.set_tcp(np.array(TCP))
    device.move_linear(REFERENCE)
    yield device
    device.close()


class Engine:
    """A Python program standing in for the engine process; started and stopped by the test."""

    def __init__(self, body: str) -> None:
        code = textwrap.dedent("""
            import signal, sys, time
            import numpy as np
            from drivers.robot import MotionEnvelope, URRobot, URRtdeSettings
            signal.signal(signal.SIGINT, signal.default_int_handler)  # even if started with SIGINT ignored
            def terminated(signum, frame):
                raise SystemExit("terminated")
            signal.signal(signal.SIGTERM, terminated)
            def say(*words):
                print(*words, flush=True)
        """) + textwrap.dedent(body)
        # stderr (the engine's and its worker's console lines) into a file: a pipe nobody reads could fill up
        self.stderr = tempfile.TemporaryFile()
        self.process = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE,
                                        stderr=self.stderr, text=True, start_new_session=True)
        self.lines: list[str] = []

    def expect(self, prefix: str, timeout: float = 30.0) -> str:
        """The next line of output that starts with ``prefix`` (the program is killed on a timeout)."""
        found: list[str] = []

        def read() -> None:
            assert self.process.stdout is not None
            for line in self.process.stdout:
                self.lines.append(line.rstrip("\n"))
                if line.startswith(prefix):
                    found.append(line.rstrip("\n"))
                    return

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        reader.join(timeout)
        if not found:
            self.stop()
            pytest.fail(f"engine printed no {prefix!r} within {timeout} s; output {self.lines}, "
                        f"stderr {self.stderr_text()[-2000:]}")
        return found[0]

    def stderr_text(self) -> str:
        self.stderr.seek(0)
        return self.stderr.read().decode(errors="replace")

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait(10)


def robot_at_reference(host: str) -> str:
    """Engine code: open a robot on the twin at ``host`` and move it to REFERENCE (indented as a body)."""
    return f"""
        robot = URRobot(URRtdeSettings(host={host!r}, connect_timeout=3.0, move_timeout=60.0),
                        envelope=MotionEnvelope.from_dict({ENVELOPE_DICT!r}))
        robot.open()
        robot.set_tcp(np.array({TCP}))
        robot.move_linear(np.array({REFERENCE.tolist()}))
    """


@pytest.fixture
def engines():
    started: list[Engine] = []

    def start(body: str) -> Engine:
        engine = Engine(body)
        started.append(engine)
        return engine

    yield start
    for engine in started:
        engine.stop()
        engine.stderr.close()


# --------------------------------------------------------------------------------------- open
def test_open_on_a_hostile_controller_fails_typed_within_its_deadline(hostile):
    """Silent from the start, or silent once the client's constructor waits (GIL held in the
    worker): a DeviceTimeout within the open deadline, and no worker left behind."""
    robot = URRobot(URRtdeSettings(host=hostile.host, connect_timeout=0.5), name="arm", envelope=ENVELOPE)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout) as raised:
        robot.open()
    elapsed = time.monotonic() - t0
    deadline = 6 * 0.5 + 2.0  # URRobot's open deadline after the worker's start
    assert elapsed < deadline + 3.0
    assert raised.value.device == "arm" and raised.value.operation == "open"
    if hostile.mode == "silent":
        assert "accepted but did not answer within 0.5 s" in raised.value.cause  # the worker's probe
    else:
        assert "did not complete the ur_rtde handshake" in raised.value.cause  # the stuck constructor
    assert robot.worker_pid is None and workers_of(os.getpid()) == []
    robot.close()  # harmless after a failed open


# --------------------------------------------------------------------------------------- crashes
@pytest.mark.parametrize("signum", [signal.SIGSEGV, signal.SIGKILL])
def test_a_killed_worker_gives_a_typed_error_and_the_next_open_works(twin, robot, signum):
    pid = robot.worker_pid
    assert pid is not None and [p.pid for p in workers_of(os.getpid())] == [pid]
    os.kill(pid, signum)
    assert wait_gone(pid, 5.0)
    with pytest.raises(DeviceConnectionError) as raised:
        robot.tcp_pose()
    assert f"killed by {signal.Signals(signum).name}" in raised.value.cause
    assert not robot.state().connected
    with pytest.raises(DeviceConnectionError, match="broken"):
        robot.move_linear(REFERENCE)

    robot.open()  # a fresh worker
    assert robot.worker_pid not in (None, pid)
    target = REFERENCE + [0.02, -0.01, 0.01, 0, 0, 0]
    robot.move_linear(target)
    np.testing.assert_allclose(twin.call("state")["tcp_pose"][:3], target[:3], atol=1e-7)  # the twin's truth
    np.testing.assert_allclose(robot.tcp_pose()[:3], target[:3], atol=1e-7)


def test_a_worker_killed_during_a_blocking_move_fails_the_move_at_once(twin, robot):
    """A 0.1 m move at 2.5 mm/s takes 2 s of wall time at ×20; SIGKILL after 0.3 s ends the call
    while the twin is still moving, not at the move's end or its deadline (20 s)."""
    pid = robot.worker_pid
    assert pid is not None
    killer = threading.Timer(0.3, os.kill, args=(pid, signal.SIGKILL))
    t0 = time.monotonic()
    killer.start()
    try:
        with pytest.raises(DeviceConnectionError, match="died") as raised:
            robot.move_linear(REFERENCE + [0, 0, 0.1, 0, 0, 0], speed=0.0025, acceleration=0.5)
    finally:
        killer.join()
    assert twin.call("state")["moving"]  # the error came before the move's end
    assert time.monotonic() - t0 < 5.0  # and long before its deadline
    assert raised.value.operation == "moveL" and "SIGKILL" in raised.value.cause
    deadline = time.monotonic() + 10.0
    while twin.call("state")["moving"]:  # the controller finishes the move (nobody stopped it)
        assert time.monotonic() < deadline
        time.sleep(0.05)
    robot.open()
    robot.move_linear(REFERENCE)
    np.testing.assert_allclose(twin.call("state")["tcp_pose"][:3], REFERENCE[:3], atol=1e-7)


def test_a_stalled_stream_is_a_typed_error_and_the_robot_recovers(twin, robot):
    """The twin stops streaming for 3 s (ur_rtde reconnects by itself after 2.5 s): the move gets a
    typed error, this process lives on, and a fresh open works."""
    twin.call("arm_fault", kind="stall", seconds=3.0)
    t0 = time.monotonic()  # the twin's next stream cycle (2 ms on) takes the fault: 3 s of wall time from then
    with pytest.raises((DeviceConnectionError, DeviceTimeout)):
        robot.move_linear(REFERENCE + [0.05, 0, 0, 0, 0, 0])
    assert time.monotonic() - t0 < 3 * robot.command_timeout + robot.command_timeout + 2.0
    time.sleep(max(0.0, t0 + 3.0 + 0.5 - time.monotonic()))  # the stall ends (0.5 s for its start's cycle)
    deadline = time.monotonic() + 10.0
    while twin.call("state")["moving"]:  # then the controller ends the move (a new one now would be refused)
        assert time.monotonic() < deadline
        time.sleep(0.05)
    robot.close()
    robot.open()
    robot.move_linear(REFERENCE)
    np.testing.assert_allclose(twin.call("state")["tcp_pose"][:3], REFERENCE[:3], atol=1e-7)


# --------------------------------------------------------------------------------------- lifetime
def test_no_worker_and_no_descriptor_outlives_close(twin):
    me = psutil.Process()
    fds_before = me.num_fds()
    robot = URRobot(URRtdeSettings(host=twin.endpoints["host"], connect_timeout=3.0), envelope=ENVELOPE)
    for _ in range(2):
        robot.open()
        pid = robot.worker_pid
        assert pid is not None and psutil.pid_exists(pid)
        robot.close()
        assert robot.worker_pid is None
        assert not psutil.pid_exists(pid)  # reaped, not even a zombie
        assert workers_of(os.getpid()) == []
    robot.close()  # twice is harmless
    deadline = time.monotonic() + 5.0
    while me.num_fds() > fds_before:  # the reply reader closes its end of the pipe once the worker is gone
        assert time.monotonic() < deadline, f"file descriptors leaked: {fds_before} -> {me.num_fds()}"
        time.sleep(0.05)


def test_no_worker_outlives_its_engine_and_a_move_in_progress_is_stopped(twin, engines):
    """kill -9 of the engine mid-move: the worker sees the pipe close, stops the move and exits."""
    engine = engines(robot_at_reference(twin.endpoints["host"]) + f"""
        say("worker", robot.worker_pid)
        robot.move_linear(np.array({(REFERENCE + [0, 0, 0.1, 0, 0, 0]).tolist()}), speed=0.002, acceleration=0.5)
        say("finished")
    """)
    worker_pid = int(engine.expect("worker").split()[1])
    time.sleep(0.5)  # 10 s of simulated motion at ×20: 0.2 of the move's 2.5 s wall time
    engine.process.kill()
    engine.process.wait(10)
    assert wait_gone(worker_pid, 5.0), "the worker outlived its engine"
    deadline = time.monotonic() + 5.0
    while twin.call("state")["moving"]:
        assert time.monotonic() < deadline, "the move went on after the engine died"
        time.sleep(0.05)
    z = twin.call("state")["tcp_pose"][2]
    assert REFERENCE[2] < z < REFERENCE[2] + 0.05  # stopped early on the way


def test_an_engine_that_exits_without_close_leaves_no_worker_and_no_motion(twin, engines):
    """Interpreter exit with the robot still open during an asynchronous move: the link's finalizer
    shuts the pipe down, and the worker stops the robot and exits by itself."""
    engine = engines(robot_at_reference(twin.endpoints["host"]) + f"""
        robot.move_linear(np.array({(REFERENCE + [0, 0, 0.1, 0, 0, 0]).tolist()}), speed=0.002, acceleration=0.5,
                          asynchronous=True)
        say("worker", robot.worker_pid)
        time.sleep(0.5)
        say("leaving")
    """)
    worker_pid = int(engine.expect("worker").split()[1])
    engine.expect("leaving")
    assert engine.process.wait(10) == 0
    assert wait_gone(worker_pid, 5.0), "the worker outlived its engine"
    deadline = time.monotonic() + 5.0
    while twin.call("state")["moving"]:
        assert time.monotonic() < deadline, "the move went on after the engine exited"
        time.sleep(0.05)
    assert REFERENCE[2] < twin.call("state")["tcp_pose"][2] < REFERENCE[2] + 0.05


def test_no_worker_outlives_its_engine_while_a_constructor_holds_the_gil(after_probe, engines):
    """The engine dies while its worker's ur_rtde constructor waits on a controller gone silent: no
    thread of the worker can run, so the kernel timer (SIGALRM) ends it."""
    engine = engines(f"""
        import threading
        robot = URRobot(URRtdeSettings(host={after_probe.host!r}, connect_timeout=1.0), envelope=MotionEnvelope())
        threading.Thread(target=robot.open, daemon=True).start()
        while robot.worker_pid is None:
            time.sleep(0.01)
        say("worker", robot.worker_pid)
        time.sleep(60)
    """)
    worker_pid = int(engine.expect("worker").split()[1])
    after_probe.wait_for_client_constructor()
    engine.process.kill()
    engine.process.wait(10)
    assert wait_gone(worker_pid, 3 * 1.0 + 1.0 + 5.0), "the worker outlived its engine"


# --------------------------------------------------------------------------------------- signals
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_the_engine_can_be_interrupted_while_open_is_pending(after_probe, engines, signum):
    """open() waits (up to 6 × 20 + 2 s) on a controller whose client constructor hangs; Ctrl-C or
    SIGTERM still interrupts the engine at once, and the worker is gone with it."""
    engine = engines(f"""
        import os
        robot = URRobot(URRtdeSettings(host={after_probe.host!r}, connect_timeout=20.0), envelope=MotionEnvelope())
        say("opening")
        t0 = time.monotonic()
        try:
            robot.open()
        except BaseException as exc:
            say("interrupted", type(exc).__name__, robot.worker_pid)
            raise
    """)
    engine.expect("opening")
    after_probe.wait_for_client_constructor()
    assert len(workers_of(engine.process.pid)) == 1
    t0 = time.monotonic()
    engine.process.send_signal(signum)
    line = engine.expect("interrupted", timeout=20.0)
    assert time.monotonic() - t0 < 10.0  # at once, against an open() deadline of 122 s
    assert line.split()[1] == ("KeyboardInterrupt" if signum == signal.SIGINT else "SystemExit")
    assert line.split()[2] == "None"  # open() cleared its worker on the way out
    engine.process.wait(10)
    assert workers_of(engine.process.pid) == []


def test_a_sigterm_handler_may_stop_and_close_the_robot_while_a_move_is_pending(twin, engines):
    """An abort from inside the signal handler, while the main thread waits in a blocking move:
    nothing deadlocks, the robot stops short of the target, the engine exits, no worker is left."""
    engine = engines(robot_at_reference(twin.endpoints["host"]) + f"""
        def abort(signum, frame):
            robot.stop(2.0)
            robot.close()
            say("aborted")
        signal.signal(signal.SIGTERM, abort)
        say("moving", robot.worker_pid)
        try:
            robot.move_linear(np.array({(REFERENCE + [0, 0, 0.1, 0, 0, 0]).tolist()}), speed=0.002, acceleration=0.5)
        except Exception as exc:
            say("move ended", type(exc).__name__)
    """)
    worker_pid = int(engine.expect("moving").split()[1])
    time.sleep(0.5)
    engine.process.send_signal(signal.SIGTERM)
    engine.expect("aborted", timeout=15.0)
    # Stopped short of the target, or its worker closed under it: a typed error either way.
    assert engine.expect("move ended").split()[2] in ("MoveFailed", "DeviceConnectionError")
    assert engine.process.wait(10) == 0
    assert wait_gone(worker_pid, 2.0)
    deadline = time.monotonic() + 5.0
    while twin.call("state")["moving"]:
        assert time.monotonic() < deadline, "the robot did not stop"
        time.sleep(0.05)
    assert REFERENCE[2] < twin.call("state")["tcp_pose"][2] < REFERENCE[2] + 0.05


def test_a_signal_handler_may_close_the_robot_while_open_is_pending(after_probe, engines):
    engine = engines(f"""
        robot = URRobot(URRtdeSettings(host={after_probe.host!r}, connect_timeout=20.0), envelope=MotionEnvelope())
        signal.signal(signal.SIGTERM, lambda signum, frame: robot.close())
        say("opening")
        try:
            robot.open()
        except Exception as exc:
            say("open ended", type(exc).__name__, robot.worker_pid)
    """)
    engine.expect("opening")
    after_probe.wait_for_client_constructor()
    engine.process.send_signal(signal.SIGTERM)
    assert engine.expect("open ended", timeout=20.0).split()[2:] == ["DeviceConnectionError", "None"]
    assert engine.process.wait(10) == 0
    assert workers_of(engine.process.pid) == []


def test_ctrl_c_interrupts_a_blocking_move_and_the_robot_can_still_be_stopped(twin, engines):
    """The engine's Ctrl-C handling (pause or abort) needs the robot right after the interrupt: the
    worker ignores the terminal's Ctrl-C and serves stop() while the interrupted move's watch ends."""
    engine = engines(robot_at_reference(twin.endpoints["host"]) + f"""
        say("moving", robot.worker_pid)
        try:
            robot.move_linear(np.array({(REFERENCE + [0, 0, 0.1, 0, 0, 0]).tolist()}), speed=0.002, acceleration=0.5)
            say("finished")
        except KeyboardInterrupt:
            say("interrupted")
            robot.stop(2.0)
            robot.wait_until_steady(5.0)
            say("stopped", robot.tcp_pose()[2], robot.state().connected)
        robot.close()
        say("closed")
    """)
    worker_pid = int(engine.expect("moving").split()[1])
    time.sleep(0.5)
    t0 = time.monotonic()
    engine.process.send_signal(signal.SIGINT)
    engine.expect("interrupted", timeout=10.0)
    assert time.monotonic() - t0 < 3.0  # the move had 4.5 s of wall time to go
    stopped = engine.expect("stopped").split()
    assert REFERENCE[2] < float(stopped[1]) < REFERENCE[2] + 0.05 and stopped[2] == "True"
    assert REFERENCE[2] < twin.call("state")["tcp_pose"][2] < REFERENCE[2] + 0.05  # the twin agrees
    engine.expect("closed")
    assert engine.process.wait(10) == 0
    assert wait_gone(worker_pid, 2.0)
