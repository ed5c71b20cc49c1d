"""Hooks: callables, entry points, shell commands, loopback HTTP; failing and slow hooks lose nothing."""

import http.server
import json
import threading
import time

import pytest

import procedures._hooks as hooks_module
from procedures._api import open_engine
from procedures._hooks import HookRunner
from procedures._models import HookSpec
from tests import fakes
from tests.fakes import FakeCell, FakeScience, write_station

EVENT = {"event": "run_finished", "run_id": "abc", "state": "FINISHED"}


@pytest.fixture
def http_server():
    received = []

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_POST(self):
            body = self.rfile.read(int(self.headers["Content-Length"]))
            received.append(json.loads(body))
            status = 500 if self.path == "/broken" else 204
            self.send_response(status)
            self.end_headers()

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}", received
    server.shutdown()
    server.server_close()
    thread.join(5)


def test_callable_hook():
    fakes.RECEIVED_EVENTS.clear()
    assert HookRunner([HookSpec(call="tests.fakes:record_event")]).emit(EVENT) == []
    assert fakes.RECEIVED_EVENTS == [EVENT]


def test_entry_point_hook(monkeypatch):
    class EntryPoint:
        def load(self):
            return fakes.record_event

    monkeypatch.setattr(hooks_module, "entry_points",
                        lambda group, name: [EntryPoint()] if (group, name) == ("opr_instrument.hooks", "cell") else [])
    fakes.RECEIVED_EVENTS.clear()
    assert HookRunner([HookSpec(entry_point="cell")]).emit(EVENT) == []
    assert fakes.RECEIVED_EVENTS == [EVENT]
    assert "no entry point 'other'" in HookRunner([HookSpec(entry_point="other")]).emit(EVENT)[0]


def test_shell_hook_gets_the_event_on_stdin_and_env(tmp_path):
    out, env = tmp_path / "stdin.json", tmp_path / "env.json"
    spec = HookSpec(shell=f'cat > {out}; printf "%s" "$INSTRUMENT_EVENT" > {env}')
    assert HookRunner([spec]).emit(EVENT) == []
    assert json.loads(out.read_text()) == EVENT == json.loads(env.read_text())


def test_http_hook_posts_to_loopback(http_server):
    url, received = http_server
    assert HookRunner([HookSpec(http=url + "/events")]).emit(EVENT) == []
    assert received == [EVENT]


def test_failing_hooks_are_reported_not_raised(http_server):
    url, _ = http_server
    failures = []
    runner = HookRunner([
        HookSpec(call="tests.fakes:failing_hook"),
        HookSpec(shell="echo broken >&2; exit 3"),
        HookSpec(http=url + "/broken"),
        HookSpec(http="http://127.0.0.1:9/closed", timeout_s=2),
        HookSpec(call="tests.fakes:no_such_function"),
    ], on_failure=lambda message, event: failures.append(message))
    messages = runner.emit(EVENT)
    assert len(messages) == 5 and failures == messages
    assert "the cell PLC is offline" in messages[0]
    assert "status 3: broken" in messages[1]
    assert "HTTP 500" in messages[2]


def test_slow_hooks_are_abandoned_at_their_timeout():
    runner = HookRunner([HookSpec(call="tests.fakes:slow_hook", timeout_s=0.2),
                         HookSpec(shell="sleep 20", timeout_s=0.3)])
    start = time.monotonic()
    messages = runner.emit(EVENT)
    assert time.monotonic() - start < 2.5  # neither the 3 s callable nor the 20 s command is waited for
    assert "did not return within 0.2 s" in messages[0]
    assert "did not finish within 0.3 s" in messages[1]


def test_hooks_only_fire_on_their_events():
    fakes.RECEIVED_EVENTS.clear()
    HookRunner([HookSpec(call="tests.fakes:record_event", events=["run_failed"])]).emit(EVENT)
    assert fakes.RECEIVED_EVENTS == []


def test_a_run_with_failing_hooks_loses_no_data(tmp_path, http_server):
    url, received = http_server
    station = write_station(tmp_path / "station.yaml")
    proc = tmp_path / "iso.yaml"
    proc.write_text(
        "procedure: iso9283_repeatability\n"
        "parameters: {cycles: 2, settle_time_s: 0, frames_per_pose: 1}\n"
        "hooks:\n"
        f"  - http: {url}/events\n"
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
    assert len(samples) == 15
    assert [e["event"] for e in received] == ["run_started"] + ["point_measured"] * 15 + ["run_finished"]
    assert received[1]["step"] == 0 and received[1]["ok"] is True and len(received[1]["pose"]) == 6
    assert sum(e["kind"] == "hook_failed" for e in events) == 15
