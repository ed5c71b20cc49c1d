"""Hooks: callables, entry points, shell commands, loopback HTTP; bounded and isolated.

Each misbehaving peer is real: a local HTTP server that hangs, trickles, answers forever or
redirects, and shell commands that outlive their deadline or escape their process group; each is
started and stopped by a fixture. Every call has a total deadline; nothing a hook does can hold up
``emit`` (the engine's step loop), and every event that is not delivered is reported.
"""

import http.server
import importlib.metadata
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid

import pytest

from procedures.engine import MAX_RESPONSE_BYTES, HookRunner, open_engine
from procedures.station import HookSpec
from tests import fakes
from tests.fakes import FakeCell, FakeScience, write_station

EVENT = {"event": "run_finished", "run_id": "abc", "state": "FINISHED"}


class _Server:
    """A loopback HTTP server in a thread; ``behaviour`` decides what each POST gets."""

    def __init__(self, behaviour):
        self.received: list[dict] = []
        self.stop = threading.Event()
        outer = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_POST(self):
                body = self.rfile.read(int(self.headers["Content-Length"]))
                outer.received.append({"path": self.path, "body": json.loads(body)})
                behaviour(self, outer)

            def log_message(self, *args):
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        # shutdown() waits for serve_forever to look at its flag: every 0.05 s rather than the default 0.5 s
        self.thread = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.05},
                                       daemon=True)
        self.thread.start()
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"

    def close(self):
        self.stop.set()  # releases the handlers that hang or trickle
        self.server.shutdown()
        self.server.server_close()
        self.thread.join(5)


@pytest.fixture
def serve():
    servers = []

    def start(behaviour):
        servers.append(_Server(behaviour))
        return servers[-1]

    yield start
    for server in servers:
        server.close()


def _ok(handler, server):
    status = 500 if handler.path == "/broken" else 204
    handler.send_response(status)
    handler.end_headers()


def _hang(handler, server):
    server.stop.wait(30)  # accepts the request and never answers


def _trickle(handler, server):
    handler.wfile.write(b"HTTP/1.1 200 OK\r\n")
    while not server.stop.is_set():  # one header byte every 50 ms, forever: every read returns something
        try:
            handler.wfile.write(b"X")
            handler.wfile.flush()
        except OSError:
            return
        server.stop.wait(0.05)


def _endless(handler, server):
    handler.send_response(200)
    handler.send_header("Content-Type", "application/octet-stream")
    handler.end_headers()
    block = b"0" * 65536
    while not server.stop.is_set():  # an endless body, as fast as the reader takes it
        try:
            handler.wfile.write(block)
        except OSError:
            return


def test_callable_hook():
    fakes.RECEIVED_EVENTS.clear()
    assert HookRunner([HookSpec(call="tests.fakes:record_event")]).call(EVENT) == []
    assert fakes.RECEIVED_EVENTS == [EVENT]


def test_entry_point_hook(monkeypatch):
    class EntryPoint:
        def load(self):
            return fakes.record_event

    monkeypatch.setattr(importlib.metadata, "entry_points",
                        lambda group, name: [EntryPoint()] if (group, name) == ("opr_instrument.hooks", "cell") else [])
    fakes.RECEIVED_EVENTS.clear()
    assert HookRunner([HookSpec(entry_point="cell")]).call(EVENT) == []
    assert fakes.RECEIVED_EVENTS == [EVENT]
    assert "no entry point 'other'" in HookRunner([HookSpec(entry_point="other")]).call(EVENT)[0]


def test_shell_hook_gets_the_event_on_stdin_and_env(tmp_path):
    out, env = tmp_path / "stdin.json", tmp_path / "env.json"
    spec = HookSpec(shell=f'cat > {out}; printf "%s" "$INSTRUMENT_EVENT" > {env}')
    assert HookRunner([spec]).call(EVENT) == []
    assert json.loads(out.read_text()) == EVENT == json.loads(env.read_text())


def test_http_hook_posts_to_loopback(serve):
    server = serve(_ok)
    assert HookRunner([HookSpec(http=server.url + "/events")]).call(EVENT) == []
    assert [r["body"] for r in server.received] == [EVENT]


def test_failing_hooks_are_reported_not_raised(serve):
    server = serve(_ok)
    with socket.socket() as closed:  # a port nobody listens on: bound, never listening
        closed.bind(("127.0.0.1", 0))
        runner = HookRunner([
            HookSpec(call="tests.fakes:failing_hook"),
            HookSpec(shell="echo broken >&2; exit 3"),
            HookSpec(http=server.url + "/broken"),
            HookSpec(http=f"http://127.0.0.1:{closed.getsockname()[1]}/closed", timeout_s=2),
            HookSpec(call="tests.fakes:no_such_function"),
        ])
        messages = runner.call(EVENT)
    assert len(messages) == 5
    assert "the cell PLC is offline" in messages[0]
    assert "status 3: broken" in messages[1]
    assert "HTTP 500" in messages[2]
    assert "ConnectionRefusedError" in messages[3]


def test_slow_hooks_are_abandoned_at_their_timeout():
    runner = HookRunner([HookSpec(call="tests.fakes:slow_hook", timeout_s=0.2),
                         HookSpec(shell="sleep 20", timeout_s=0.3)])
    start = time.monotonic()
    messages = runner.call(EVENT)
    assert time.monotonic() - start < 2.5  # neither the 3 s callable nor the 20 s command is waited for
    assert "did not return within 0.2 s" in messages[0]
    assert "did not finish within 0.3 s" in messages[1]


def test_hooks_only_fire_on_their_events():
    fakes.RECEIVED_EVENTS.clear()
    HookRunner([HookSpec(call="tests.fakes:record_event", events=["run_failed"])]).call(EVENT)
    assert fakes.RECEIVED_EVENTS == []


# ---------------------------------------------------------------------------- hostile peers
def test_a_hanging_server_costs_one_deadline(serve):
    server = serve(_hang)
    start = time.monotonic()
    (message,) = HookRunner([HookSpec(http=server.url, timeout_s=0.5)]).call(EVENT)
    assert time.monotonic() - start < 3
    assert "no complete answer within 0.5 s" in message


def test_a_trickling_server_is_cut_at_the_total_deadline(serve):
    """Every read gets a byte within the socket timeout: only a deadline on the whole call ends it."""
    server = serve(_trickle)
    start = time.monotonic()
    (message,) = HookRunner([HookSpec(http=server.url, timeout_s=0.6)]).call(EVENT)
    assert time.monotonic() - start < 3
    assert "within 0.6 s" in message


def test_an_endless_answer_is_not_read_past_the_limit(serve):
    import resource

    server = serve(_endless)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    (message,) = HookRunner([HookSpec(http=server.url, timeout_s=5)]).call(EVENT)
    grown_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
    assert f"longer than {MAX_RESPONSE_BYTES} bytes" in message
    assert grown_kib < 50_000  # the earlier client grew by gigabytes; this one reads 64 KiB


def test_redirects_are_refused_not_followed(serve):
    target = serve(_ok)

    def redirect(handler, server):
        handler.send_response(307)
        handler.send_header("Location", target.url + "/elsewhere")
        handler.end_headers()

    server = serve(redirect)
    (message,) = HookRunner([HookSpec(http=server.url + "/events", timeout_s=2)]).call(EVENT)
    assert "HTTP 307" in message and "not followed" in message
    assert target.received == []  # the redirect's target never heard from us


def test_a_shell_hook_that_escapes_its_process_group_does_not_block(tmp_path):
    """``setsid cmd &`` leaves a process in a new session holding the hook's stdout/stderr: the hook
    returns when its shell does, not when that process ends."""
    pid_file = tmp_path / "escaped.pid"
    spec = HookSpec(shell=f"setsid sh -c 'echo $$ > {pid_file}; exec sleep 30' & sleep 0.2", timeout_s=5)
    start = time.monotonic()
    try:
        assert HookRunner([spec]).call(EVENT) == []
        assert time.monotonic() - start < 3
    finally:
        for _ in range(50):
            if pid_file.exists() and pid_file.read_text().strip():
                break
            time.sleep(0.05)
        if pid_file.exists() and pid_file.read_text().strip():
            try:
                os.kill(int(pid_file.read_text()), 9)  # the process this test started, by its id
            except ProcessLookupError:
                pass


def test_a_shell_hook_past_its_deadline_is_killed_with_its_children(tmp_path):
    pid_file = tmp_path / "child.pid"
    spec = HookSpec(shell=f"sleep 30 & echo $! > {pid_file}; wait", timeout_s=0.5)
    start = time.monotonic()
    (message,) = HookRunner([spec]).call(EVENT)
    assert time.monotonic() - start < 4
    assert "process group and descendants stopped" in message
    child = int(pid_file.read_text())
    for _ in range(100):  # the group's SIGKILL reaches the background child too
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            break
        with open(f"/proc/{child}/stat") as stat:
            if stat.read().split(")")[1].split()[0] == "Z":  # dead, waiting for its reaper
                break
        time.sleep(0.05)
    else:
        pytest.fail("the hook's background child outlived the deadline")


def test_emit_never_waits_and_close_reports_what_was_not_delivered(serve):
    server = serve(_hang)
    failures = []
    runner = HookRunner([HookSpec(http=server.url, timeout_s=0.3)], on_failure=lambda m, e: failures.append(m))
    start = time.monotonic()
    for number in range(20):
        runner.emit({**EVENT, "event": "point_measured", "step": number})
    assert time.monotonic() - start < 0.5  # queued, not delivered, in this thread
    runner.close(grace_s=1.0)
    messages = runner.take_failures()
    assert len(messages) == 20 and messages == failures  # each event: failed, or reported as not delivered
    assert sum("not delivered" in m for m in messages) >= 15


def test_a_run_with_failing_hooks_loses_no_data(tmp_path, serve):
    server = serve(_ok)
    station = write_station(tmp_path / "station.yaml")
    proc = tmp_path / "iso.yaml"
    proc.write_text(
        "procedure: iso9283_repeatability\n"
        "parameters: {cycles: 2, settle_time_s: 0, frames_per_pose: 1}\n"
        "hooks:\n"
        f"  - http: {server.url}/events\n"
        "    on: [run_started, point_measured, run_finished]\n"
        "  - call: tests.fakes:failing_hook\n"
        "    events: [point_measured]\n"
    )
    cell = FakeCell(seed=4)
    with open_engine(tmp_path / "runs", procedure=proc, station=station, science=FakeScience(cell),
                     devices=cell.devices(), operator=cell.operator) as engine:
        assert engine.execute() == "FINISHED"
        samples = engine.store.samples(engine.run_id)
        events = engine.store.events(engine.run_id)
    received = [r["body"] for r in server.received]
    assert len(samples) == 15
    assert [e["event"] for e in received] == ["run_started"] + ["point_measured"] * 15 + ["run_finished"]
    assert received[1]["step"] == 0 and received[1]["ok"] is True and len(received[1]["pose"]) == 6
    assert sum(e["kind"] == "hook_failed" for e in events) == 15


# ------------------------------------------------------------- no hook process outlives its deadline or its run
def _carrying(mark: str) -> list[int]:
    """Live (not zombie) processes whose environment holds ``TEST_MARK=mark``: what this test started."""
    found = []
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/environ", "rb") as environ:
                if f"TEST_MARK={mark}".encode() not in environ.read().split(b"\0"):
                    continue
            with open(f"/proc/{name}/stat") as stat:
                if stat.read().rsplit(")", 1)[1].split()[0] == "Z":
                    continue
        except OSError:
            continue
        found.append(int(name))
    return found


def _wait_for(condition, seconds: float) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.05)
    return condition()


@pytest.fixture
def mark():
    """A mark for the processes a test's hooks start (``export TEST_MARK=…`` in the command, inherited by
    every descendant); afterwards whatever still carries it is killed, by its process id."""
    value = uuid.uuid4().hex
    yield value
    for pid in _carrying(value):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def test_a_hook_still_running_when_the_run_ends_is_stopped(mark):
    """A hook whose deadline lies past the run's end is stopped when the runner closes (it was left running,
    reparented to init: ``sleep 4244`` with ppid 1), with its background and ``setsid`` children."""
    spec = HookSpec(shell=f"export TEST_MARK={mark}; setsid sleep 300 & sleep 300 & sleep 300", timeout_s=60)
    runner = HookRunner([spec])
    runner.emit(EVENT)
    assert _wait_for(lambda: len(_carrying(mark)) >= 3, 5)
    start = time.monotonic()
    runner.close(grace_s=0.5)  # the run's end
    assert _carrying(mark) == []
    assert time.monotonic() - start < 5
    (message,) = runner.take_failures()
    assert "still running when the run ended; its processes stopped" in message


def test_setsid_children_do_not_outlive_the_deadline(mark):
    """The shell returns at once, leaving ``setsid sleep 300 &``: it may run until the call's deadline, no longer."""
    spec = HookSpec(shell=f"export TEST_MARK={mark}; setsid sleep 300 & setsid sh -c 'sleep 300 & sleep 300' &",
                    timeout_s=1.5)
    start = time.monotonic()
    assert HookRunner([spec]).call(EVENT) == []
    assert time.monotonic() - start < 1.5
    assert _wait_for(lambda: len(_carrying(mark)) >= 3, 1)  # running, within the deadline
    assert _wait_for(lambda: _carrying(mark) == [], 4)  # then stopped: SIGTERM at 1.5 s
    assert time.monotonic() - start < 5


def test_children_of_a_hook_past_its_deadline_are_stopped_wherever_they_moved(mark):
    spec = HookSpec(shell=f"export TEST_MARK={mark}; setsid sleep 300 & sleep 300", timeout_s=0.5)
    start = time.monotonic()
    (message,) = HookRunner([spec]).call(EVENT)
    assert "did not finish within 0.5 s" in message
    assert _carrying(mark) == []
    assert time.monotonic() - start < 4


def test_a_process_that_ends_takes_its_hooks_with_it(mark, tmp_path):
    """A command that exits while hooks still run (no ``close``: an exit, an unhandled error) stops them."""
    script = (
        "import sys, time\n"
        "from procedures.engine import HookRunner\n"
        "from procedures.station import HookSpec\n"
        f"spec = HookSpec(shell='export TEST_MARK={mark}; setsid sleep 300 & sleep 300', timeout_s=60)\n"
        "runner = HookRunner([spec])\n"
        "runner.emit({'event': 'run_finished', 'run_id': 'abc', 'state': 'FINISHED'})\n"
        # exit once both sleeps run (found by their mark, within 10 s), rather than after a fixed second
        "from pathlib import Path\n"
        f"marked = b'TEST_MARK={mark}'\n"
        "def running():\n"
        "    found = 0\n"
        "    for entry in Path('/proc').iterdir():\n"
        "        try:\n"
        "            found += entry.name.isdigit() and marked in (entry / 'environ').read_bytes().split(b'\\0')\n"
        "        except OSError:\n"
        "            pass\n"
        "    return found\n"
        "deadline = time.monotonic() + 10\n"
        "while running() < 2:\n"
        "    assert time.monotonic() < deadline, 'the hook never started its two sleeps'\n"
        "    time.sleep(0.02)\n"
        "sys.exit(0)\n"
    )
    started = subprocess.run([sys.executable, "-c", script], timeout=20, capture_output=True, text=True)
    assert started.returncode == 0, started.stderr
    assert _carrying(mark) == []


def test_a_run_leaves_no_hook_process_behind(tmp_path, mark):
    station = write_station(tmp_path / "station.yaml")
    proc = tmp_path / "iso.yaml"
    proc.write_text(
        "procedure: iso9283_repeatability\n"
        "parameters: {cycles: 2, settle_time_s: 0, frames_per_pose: 1}\n"
        "hooks:\n"
        f"  - shell: 'export TEST_MARK={mark}; setsid sleep 300 &'\n"
        "    on: [run_started]\n"
        "    timeout_s: 60\n"
        f"  - shell: 'export TEST_MARK={mark}; sleep 300'\n"
        "    on: [run_finished]\n"
        "    timeout_s: 2\n"
    )
    cell = FakeCell(seed=4)
    start = time.monotonic()
    with open_engine(tmp_path / "runs", procedure=proc, station=station, science=FakeScience(cell),
                     devices=cell.devices(), operator=cell.operator) as engine:
        assert engine.execute() == "FINISHED"
    assert _carrying(mark) == []
    assert time.monotonic() - start < 15
