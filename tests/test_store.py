"""The run store: durable samples, no duplicates, and a kill -9 in the middle of a run loses nothing."""

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from procedures.cli import main
from procedures.engine import open_engine
from procedures.store import (
    Commanded,
    CorrectedPose,
    DuplicateStep,
    PoseQuality,
    Reference,
    RunState,
    RunStore,
    Sample,
    SolvedPose,
)
from tests.fakes import FakeCell, FakeScience, write_station

ROOT = Path(__file__).resolve().parents[1]


def test_a_step_cannot_be_stored_twice(tmp_path):
    with RunStore(tmp_path) as store:
        run_id = store.create_run(procedure="iso9283_repeatability", parameters={}, station={}, software_version="t")
        store.add_sample(Sample(run_id, 0, "iso/c000/P1", "iso", solved=SolvedPose(pose=(0.0,) * 6)))
        with pytest.raises(DuplicateStep):
            store.add_sample(Sample(run_id, 0, "iso/c000/P1", "iso"))
        assert store.committed_steps(run_id) == {0}
        assert store.get_run(run_id[:6])["id"] == run_id  # a prefix is enough


def test_store_uses_wal_and_full_sync(tmp_path):
    with RunStore(tmp_path) as store:
        assert store._db.rows("PRAGMA journal_mode")[0]["journal_mode"] == "wal"
        assert store._db.rows("PRAGMA synchronous")[0]["synchronous"] == 2  # FULL


def _committed(db: Path) -> int:
    if not db.exists():
        return 0
    with sqlite3.connect(db, timeout=10) as conn:
        try:
            return conn.execute("SELECT COUNT(*) FROM samples").fetchone()[0]
        except sqlite3.OperationalError:
            return 0


def test_kill_9_mid_run_then_resume_loses_and_duplicates_nothing(tmp_path):
    station = write_station(tmp_path / "station.yaml")
    procedure = tmp_path / "iso.yaml"
    procedure.write_text("procedure: iso9283_repeatability\n"
                         "parameters: {cycles: 6, settle_time_s: 0, frames_per_pose: 1}\n")
    runs = tmp_path / "runs"
    child = subprocess.Popen(
        [sys.executable, "-m", "tests.fakes", str(runs), str(station), str(procedure), "--move-delay", "0.05"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        deadline = time.monotonic() + 60
        while _committed(runs / "runs.sqlite") < 8:
            assert child.poll() is None, child.stderr.read()
            assert time.monotonic() < deadline, "child made no progress"
            time.sleep(0.02)
        os.kill(child.pid, signal.SIGKILL)  # our own child, by its id
        child.wait(10)
    finally:
        if child.poll() is None:
            os.kill(child.pid, signal.SIGKILL)
            child.wait(10)
        child.stdout.close()
        child.stderr.close()

    with RunStore(runs) as store:
        (run,) = store.list_runs()
        assert run["state"] == "RUNNING"  # it never got to say anything else
        before = {s.step_index: s for s in store.samples(run["id"])}
    assert len(before) >= 8 and sorted(before) == list(range(len(before)))
    assert len(before) < 35

    cell = FakeCell(seed=5)
    with open_engine(runs, run_id=run["id"], science=FakeScience(cell), devices=cell.devices(),
                     operator=cell.operator) as engine:
        assert engine.execute() == "FINISHED"
        after = engine.store.samples(run["id"])
    assert [s.step_index for s in after] == list(range(35))
    for s in after[: len(before)]:  # the committed samples are exactly the ones the killed process wrote
        assert s.solved == before[s.step_index].solved and s.t_committed == before[s.step_index].t_committed
    assert cell.moves == 35 - len(before)  # only the missing steps were measured again


def test_typed_blocks_round_trip_through_their_stored_form():
    quality = PoseQuality(residual_rms=1e-7, pose_std=(1e-6,) * 6, attempts=2)
    solved = SolvedPose(pose=(0.01, 0.02, 0.03, 1e-4, -2e-4, 3e-4), quality=quality,
                        per_frame=((0.01,) * 6, (0.02,) * 6))
    corrected = CorrectedPose(pose=(0.011,) * 6, records=("sha256:1",), flags=("x beyond the record's range",),
                              direction={"x": 1, "y": None, "z": -1, "a": None, "b": None, "c": None})
    reference = Reference(value=0.02, robot_tcp_pose=(0.45, -0.1, 0.27, 3.14, 0.0, 0.0), approach=1,
                          environment={"air_temperature_k": 293.15}, readings={"interferometer_m": 0.0199})
    commanded = Commanded(tcp_pose=(0.45, -0.1, 0.27, 3.14, 0.0, 0.0), nominal=0.02)
    assert SolvedPose.from_stored(solved.to_stored()) == solved
    assert CorrectedPose.from_stored(corrected.to_stored()) == corrected
    assert Reference.from_stored(reference.to_stored()) == reference
    assert Commanded.from_stored(commanded.to_stored()) == commanded
    sample = Sample("r", 3, "disp/x/g0/r0/p03", "calibration", label="x=15 mm", commanded=commanded, solved=solved,
                    corrected=corrected, reference=reference, meta={"axis": "x"}, frames=("frames/a.npy",))
    assert Sample.from_row(sample.to_row()) == sample and sample.pose == corrected.pose
    # What an earlier version stored reads back: a key it did not write is None, its session record is not a reading.
    old = SolvedPose.from_stored({"pose": [0, 0, 0, 0, 0, 0], "residual_rms": 1e-7})
    assert old.pose == (0.0,) * 6 and old.quality == PoseQuality(residual_rms=1e-7) and old.per_frame is None
    assert Reference.from_stored({"approach": {"x": 1}, "session": {"started": 1.0}}).readings == {}


def test_session_conditions_are_a_run_level_record_written_once_per_session(tmp_path, capsys):
    """A session's test conditions go to their own table with the session's first sample, never into a
    sample; a resume adds its own; the analysis sees both (docs/results.md, test_conditions.sessions)."""
    truth = tmp_path / "truth.jsonl"
    station = write_station(tmp_path / "station.yaml", truth_log=str(truth))
    procedure = tmp_path / "iso.yaml"
    procedure.write_text("procedure: iso9283_repeatability\n"
                         "parameters: {cycles: 2, settle_time_s: 0, frames_per_pose: 1, operator: A. Tester}\n")
    cell = FakeCell(seed=4, truth_log=truth)

    def engine(**kwargs):
        return open_engine(tmp_path / "runs", science=FakeScience(cell), devices=cell.devices(),
                           operator=cell.operator, **kwargs)

    def pause_at_six(event):
        if event["event"] == "progress" and event["done"] == 6:
            first.request_pause("end of shift")

    with engine(procedure=procedure, station=station, listener=pause_at_six, pause_timeout_s=0.1) as first:
        assert first.execute() == RunState.PAUSED
        run_id = first.run_id
        (session,) = first.store.sessions(run_id)
    assert session.robot["serial_number"] == "20235500123" and session.operator["name"] == "A. Tester"
    with engine(run_id=run_id) as second:
        assert second.execute() == RunState.FINISHED
        sessions = second.store.sessions(run_id)
        results = second.store.get_run(run_id)["results"]
    assert [s.started for s in sessions] == sorted(s.started for s in sessions) and sessions[0] == session
    assert results["test_conditions"]["sessions"] == [s.to_stored() for s in sessions] and len(sessions) == 2
    with sqlite3.connect(tmp_path / "runs" / "runs.sqlite") as db:
        assert db.execute("SELECT COUNT(*) FROM session_conditions WHERE run_id = ?", (run_id,)).fetchone() == (2,)
        references = [row[0] for row in db.execute("SELECT reference FROM samples WHERE run_id = ?", (run_id,))]
    assert references and not any('"session"' in (reference or "") for reference in references)
    assert main(["export", run_id, "--json", "--runs-dir", str(tmp_path / "runs")]) == 0
    assert json.loads(capsys.readouterr().out)["sessions"] == [s.to_stored() for s in sessions]
