"""The run store: durable samples, no duplicates, and a kill -9 in the middle of a run loses nothing."""

import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from procedures.engine import open_engine
from procedures.store import DuplicateStep, RunStore
from tests.fakes import FakeCell, FakeScience, write_station

ROOT = Path(__file__).resolve().parents[1]


def test_a_step_cannot_be_stored_twice(tmp_path):
    with RunStore(tmp_path) as store:
        run_id = store.create_run(procedure="iso9283_repeatability", parameters={}, station={}, software_version="t")
        store.add_sample(run_id, 0, "iso/c000/P1", "iso", solved={"pose": [0.0] * 6})
        with pytest.raises(DuplicateStep):
            store.add_sample(run_id, 0, "iso/c000/P1", "iso")
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
