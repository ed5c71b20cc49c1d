"""The kinds that measure while the robot moves, on the fake cell (fast): the engine, the stored
streams, resume, the live events — against the fake cell's known motion (``FakeCell.true_at``)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from instrument.iso9283 import pose_stabilisation
from procedures.engine import open_engine
from procedures.kinds import COLUMNS, StreamRecord
from procedures.kinds.dynamic import tool_poses
from procedures.station import ur_to_matrix
from procedures.store import LATEST, RunState, RunStore
from tests.fakes import TOOL_IN_OPR, FakeCell, FakeScience, write_station

pytestmark = pytest.mark.timeout(120)

FAST = {"cycles": 2, "speeds_percent": [100, 20], "rate_hz": 200.0, "rest_s": 0.0, "cube_edge_m": 0.04,
        "cube_center_m": [0.0, 0.0, 0.0], "min_poses": 10}


def _procedure(tmp_path: Path, kind: str, **parameters) -> Path:
    path = tmp_path / f"{kind}.yaml"
    path.write_text(yaml.safe_dump({"procedure": kind, "parameters": {**FAST, **parameters}}), encoding="utf-8")
    return path


def _cell() -> FakeCell:
    cell = FakeCell(seed=5)
    cell.timed_moves = True
    return cell


def _run(tmp_path: Path, cell: FakeCell, procedure: Path, **options):
    station = write_station(tmp_path / "station.yaml")
    engine_cm = open_engine(tmp_path / "runs", procedure=procedure, station=station, science=FakeScience(cell),
                            devices=cell.devices(), operator=cell.operator, **options)
    return engine_cm


def test_stabilisation_run_matches_the_known_ring_down(tmp_path):
    cell = _cell()
    events: list[dict] = []
    with _run(tmp_path, cell, _procedure(tmp_path, "iso9283_stabilisation", window_s=0.5, band_um=10.0),
              listener=events.append) as engine:
        assert engine.execute() == RunState.FINISHED, engine.store.get_run(engine.run_id)["reason"]
        run = engine.store.get_run(engine.run_id)
        streams = engine.store.streams(engine.run_id)
        samples = engine.store.samples(engine.run_id)
    results = run["results"]
    assert len(samples) == 4 and all(s.ok for s in samples) and sorted(streams) == [0, 1, 2, 3]
    opr_to_tool = ur_to_matrix(TOOL_IN_OPR)
    for move in results["moves"]:
        record = StreamRecord.from_stored(streams[move["step"]])
        assert streams[move["step"]].columns == list(COLUMNS) and streams[move["step"]].samples == len(record)
        assert np.all(np.diff(record.t) > 0) and record.dropped == 0
        # The camera clocks were offset by up to 0.3 s: the trigger line's pairs put them back.
        pulses = record.t - 0.5e-3
        assert np.allclose(np.diff(pulses), 1 / 200.0, atol=1e-9)
        # The same function on the fake's truth at the same instants.
        truth = tool_poses(cell.true_at(record.t), opr_to_tool)
        true = pose_stabilisation(record.t, truth[:, :3], move["t_signal"], 10e-6)
        assert abs(move["stabilisation_time"] - true.stabilisation_time) <= 1 / 200.0
        assert move["overshoot"] == pytest.approx(true.overshoot, abs=2e-6)
        assert move["u_overshoot"] is not None and 0 < move["u_overshoot"] < 5e-6
    fast = next(s for s in results["settings"] if s["speed_percent"] == 100)
    slow = next(s for s in results["settings"] if s["speed_percent"] == 20)
    # 80 µm per m/s of ring-down at 0.5 m/s vs 0.1 m/s: the faster arrival overshoots more and settles later.
    assert fast["overshoot"]["mean"] > 3 * slow["overshoot"]["mean"]
    assert fast["stabilisation_time"]["mean"] > slow["stabilisation_time"]["mean"]
    assert results["band"] == pytest.approx(10e-6) and results["band_source"] == "parameter band_um"
    assert results["positioning_time"]["minimum"] > 0
    # One live event per streamed second at least, with the pose and the distance to the target.
    live = [e for e in events if e["event"] == "stream"]
    assert len(live) >= 4
    assert {"run_id", "t", "pose", "quality", "rate_hz", "dropped", "distance_to_target"} <= set(live[0])
    assert len(live[0]["pose"]) == 6 and live[0]["rate_hz"] == 200.0


def test_dropped_triggers_are_counted_never_filled(tmp_path):
    cell = _cell()
    cell.stream_drops = {3, 4, 5}
    with _run(tmp_path, cell, _procedure(tmp_path, "iso9283_stabilisation", cycles=2, speeds_percent=[100],
                                         window_s=0.3)) as engine:
        assert engine.execute() == RunState.FINISHED
        streams = engine.store.streams(engine.run_id)
    for stored in streams.values():
        record = StreamRecord.from_stored(stored)
        assert record.dropped == 3 and not {3, 4, 5} & set(record.index.tolist())
        assert record.meta["missing_frames"] == {"fake drop": 9}


def test_a_short_stream_fails_the_move_instead_of_giving_a_partial_figure(tmp_path):
    cell = _cell()
    procedure = _procedure(tmp_path, "iso9283_stabilisation", cycles=2, speeds_percent=[100], window_s=0.3,
                           min_poses=1000, max_failed_samples=5)
    with _run(tmp_path, cell, procedure) as engine:
        assert engine.execute() == RunState.FINISHED
        run_id = engine.run_id
        samples = engine.store.samples(run_id)
    assert not any(s.ok for s in samples) and "fewer than min_poses = 1000" in samples[0].error


def test_pause_and_resume_keep_every_committed_move_once(tmp_path):
    cell = _cell()
    procedure = _procedure(tmp_path, "iso9283_stabilisation", window_s=0.3)
    measured: list[int] = []

    def listener(event: dict) -> None:
        if event["event"] == "point_measured":
            measured.append(event["step"])
            if len(measured) == 2:
                engine.request_pause("test")

    with _run(tmp_path, cell, procedure, listener=listener, pause_handler=lambda _: "detach") as engine:
        assert engine.execute() == RunState.PAUSED
        run_id = engine.run_id
        first = engine.store.streams(run_id)
    assert sorted(first) == [0, 1]
    station = tmp_path / "station.yaml"
    with open_engine(tmp_path / "runs", run_id=run_id, station=station, science=FakeScience(cell),
                     devices=cell.devices(), operator=cell.operator, listener=listener) as engine:
        assert engine.execute() == RunState.FINISHED
    with RunStore(tmp_path / "runs") as store:
        streams = store.streams(run_id)
        samples = store.samples(run_id)
    assert sorted(streams) == [0, 1, 2, 3] and [s.step_index for s in samples] == [0, 1, 2, 3]
    assert all(streams[k].data == first[k].data for k in (0, 1))  # untouched by the resume
    assert measured == [0, 1, 2, 3]  # each move measured once


def test_path_run_gives_every_figure_and_the_export_carries_the_streams(tmp_path, capsys):
    from procedures.cli import main

    cell = _cell()
    cell.ring_amplitude_per_speed = 0.0
    cell.max_move_duration = 5.0  # the fake moves at the commanded speed
    procedure = _procedure(tmp_path, "iso9283_path", hold_s=0.05, settle_time_s=0.0, frames_per_pose=1,
                           speeds_percent=[40], apply_compensation=False)
    with _run(tmp_path, cell, procedure) as engine:
        assert engine.execute() == RunState.FINISHED, engine.store.get_run(engine.run_id)["reason"]
        run = engine.store.get_run(engine.run_id)
    results = run["results"]
    assert results["transform"]["fitted"] and results["transform"]["points"] == 5
    setting = results["settings"][0]
    for key in ("leg_1", "leg_2", "circle"):
        assert "error" not in setting[key], setting[key]
        assert setting[key]["at_p"] >= 0 and setting[key]["rt_p"] >= 0
    # The fake's line legs are straight: AT_p is its instrument error (±50 µm, fitted frame) at most.
    assert setting["leg_1"]["at_p"] < 150e-6
    assert {"cr", "co"} <= set(setting["corner"]) and {"av", "rv", "fv"} <= set(setting["velocity"])
    # A constant-speed fake move: the measured mean speed on the leg is the commanded one (AV ≈ 0).
    assert abs(setting["velocity"]["av"]) < 0.02 and setting["velocity"]["commanded"] == pytest.approx(0.2)
    assert main(["export", run["id"][:8], "--runs-dir", str(tmp_path / "runs"), "--json", "--streams"]) == 0
    exported = json.loads(capsys.readouterr().out)
    streams = exported["streams"]
    assert len(streams) == 4 and len(streams[0]["t"]) == len(streams[0]["pose"]) > 10
    assert main(["report", run["id"][:8], "--runs-dir", str(tmp_path / "runs")]) == 0
    html = (tmp_path / "runs" / run["id"] / "report.html").read_text(encoding="utf-8")
    assert "AT_p" in html and "CR" in html and "<svg" in html


@pytest.fixture
def child_processes():
    """Every child a test starts is killed (by pid) and reaped at the end, whatever happened."""
    started: list[subprocess.Popen] = []
    yield started
    for child in started:
        if child.poll() is None:
            os.kill(child.pid, signal.SIGKILL)
        child.wait(30)


def test_kill_9_mid_run_then_resume_keeps_every_committed_move_once(tmp_path, child_processes):
    station = write_station(tmp_path / "station.yaml")
    procedure = _procedure(tmp_path, "iso9283_stabilisation", cycles=4, speeds_percent=[100], window_s=0.4)
    runs = tmp_path / "runs"
    root = Path(__file__).resolve().parents[1]
    child = subprocess.Popen([sys.executable, "-m", "tests.fakes", str(runs), str(station), str(procedure), "--timed"],
                             cwd=root, stdout=subprocess.PIPE, text=True)
    child_processes.append(child)
    run_id = child.stdout.readline().strip() if child.stdout else ""
    deadline = time.monotonic() + 60
    before: dict = {}
    while len(before) < 2:
        assert time.monotonic() < deadline, "the child committed no moves in 60 s"
        time.sleep(0.05)
        with RunStore(runs) as store:
            before = store.streams(run_id)
    os.kill(child.pid, signal.SIGKILL)
    child.wait(30)
    with RunStore(runs) as store:
        before = store.streams(run_id)
        assert store.get_run(run_id)["state"] == "RUNNING" and 2 <= len(before) < 4
        assert sorted(before) == sorted(s.step_index for s in store.samples(run_id))  # a stream only with its sample
    resumed = subprocess.run([sys.executable, "-m", "tests.fakes", str(runs), str(station), str(procedure),
                              "--timed", "--resume", run_id], cwd=root, capture_output=True, text=True, timeout=120)
    assert resumed.stdout.split()[-1] == "FINISHED", resumed.stderr[-2000:]
    with RunStore(runs) as store:
        after = store.streams(run_id)
        samples = store.samples(run_id)
        events = store.events(run_id)
    assert sorted(after) == [0, 1, 2, 3] and [s.step_index for s in samples] == [0, 1, 2, 3]
    assert all(after[k].data == before[k].data for k in before)  # committed moves untouched
    assert "resumed after" in " ".join(str(e["message"]) for e in events)


def test_streams_round_trip_on_postgresql(tmp_path):
    from tests._postgres import postgres_server

    with postgres_server() as server:
        url = server.new_database()
        cell = _cell()
        procedure = _procedure(tmp_path, "iso9283_stabilisation", cycles=2, speeds_percent=[100], window_s=0.3)
        with _run(tmp_path, cell, procedure, store=url) as engine:
            assert engine.execute() == RunState.FINISHED
            run_id = engine.run_id
        assert not (tmp_path / "runs" / "runs.sqlite").exists()
        with RunStore(tmp_path / "runs", url=url) as store:
            streams = store.streams(run_id)
            version = store._db.rows("SELECT MAX(version) AS v FROM schema_version")[0]["v"]
            results = store.get_run(run_id)["results"]
        assert version == LATEST and sorted(streams) == [0, 1]  # the streams table came with version 5
        for step, stored in streams.items():
            record = StreamRecord.from_stored(stored)
            assert len(record) > 50 and record.meta["rate_hz"] == 200.0
            move = next(m for m in results["moves"] if m["step"] == step)
            assert move["poses"] == len(record)
