"""kill -9 at a random (seeded) moment of each procedure, then ``instrument resume`` to FINISHED:
nothing committed is lost, duplicated or changed, the calibration's datum is re-established where
the kill left a group half done, and the report keeps the truth of the samples measured before the
crash (the new cell gets its own folder; the old truth log is kept).

The displacement calibration is killed exactly at a repeat boundary: a resumed cell that replayed
the first cell's noise once made repeat 2 bit-identical to repeat 1, and the analysis failed on the
zero noise floor at every resume. The new cell is session 1 of the run: the same physics, fresh
noise. The ISO run is resumed with a plain ``instrument resume RUN``, which starts a simulated cell
by itself for a run measured on one (it once tried the dead cell's address and FAILED the run)."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow

COMMON = "settle_time_s: 0.05, frames_per_pose: 1"
PROCEDURES = {
    "iso9283_repeatability": f"procedure: iso9283_repeatability\nparameters: {{cycles: 2, {COMMON}}}\n",
    "displacement_calibration": ("procedure: displacement_calibration\nparameters: {axes: [y], groups: 1, "
                                 "group_start_offsets_mm: [[0, 0, 0]], repeats: 2, step_mm: 10, stop_mm: 40, "
                                 f"interferometer_average_s: 0.05, {COMMON}}}\n"),
    "angle_calibration": ("procedure: angle_calibration\nparameters: {axes: [x], groups: 1, "
                          "group_start_offsets_deg: [0.0], repeats: 2, step_deg: 0.5, table_speed_deg_s: 20, "
                          f"{COMMON}}}\n"),
}


def _samples(db: Path) -> list[dict]:
    if not db.exists():
        return []
    with sqlite3.connect(db, timeout=10) as conn:
        conn.row_factory = sqlite3.Row
        try:
            return [dict(row) for row in conn.execute("SELECT * FROM samples ORDER BY step_index")]
        except sqlite3.OperationalError:
            return []


def _kill_with_descendants(process: subprocess.Popen) -> None:
    """SIGKILL the run (our child) and then the simulated cell it had started (its children), by pid."""
    family = psutil.Process(process.pid).children(recursive=True)
    os.kill(process.pid, signal.SIGKILL)
    process.wait(30)
    for member in family:
        try:
            member.kill()
        except psutil.NoSuchProcess:
            pass
    psutil.wait_procs(family, timeout=30)


@pytest.mark.timeout(300)
@pytest.mark.parametrize("number, name", list(enumerate(PROCEDURES)), ids=list(PROCEDURES))
def test_kill_9_at_a_random_moment_then_resume_to_finished(tmp_path, number, name):
    rng = np.random.default_rng(1200 + number)
    procedure = tmp_path / f"{name}.yaml"
    procedure.write_text(PROCEDURES[name], encoding="utf-8")
    runs = tmp_path / "runs"
    child = subprocess.Popen([sys.executable, "-m", "procedures.cli", "run", str(procedure), "--station", "sim",
                              "--seed", "5", "--runs-dir", str(runs), "--jsonl"], cwd=ROOT,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    # Committed samples, then a random moment within the next step; the calibration right after repeat 1.
    at_boundary = name == "displacement_calibration"
    kill_after = 5 if at_boundary else int(rng.integers(2, 8))
    try:
        deadline = time.monotonic() + 120
        while len(_samples(runs / "runs.sqlite")) < kill_after:
            assert child.poll() is None, child.stderr.read()
            assert time.monotonic() < deadline, "the run made no progress"
            time.sleep(0.01)
        time.sleep(0.0 if at_boundary else float(rng.uniform(0.0, 0.5)))
        _kill_with_descendants(child)
    finally:
        if child.poll() is None:
            _kill_with_descendants(child)
        child.stderr.close()
    before = {s["step_index"]: s for s in _samples(runs / "runs.sqlite")}
    assert len(before) >= kill_after and sorted(before) == list(range(len(before)))
    with sqlite3.connect(runs / "runs.sqlite") as conn:
        run_id, state, total = conn.execute("SELECT id, state, total_steps FROM runs").fetchone()
    assert state == "RUNNING" and len(before) < total  # killed mid-run, it could not say anything else
    (first_cell,) = (runs / "sim").iterdir()
    truth_before = (first_cell / "truth.jsonl").read_bytes()

    station = [] if name == "iso9283_repeatability" else ["--station", "sim"]
    resumed = subprocess.run([sys.executable, "-m", "procedures.cli", "resume", run_id, *station,
                              "--runs-dir", str(runs), "--jsonl"], cwd=ROOT, capture_output=True, text=True,
                             timeout=240)
    assert resumed.returncode == 0, (resumed.stderr[-3000:], resumed.stdout[-3000:])
    done = json.loads(resumed.stdout.strip().splitlines()[-1])
    assert done["state"] == "FINISHED", done

    after = _samples(runs / "runs.sqlite")
    assert [s["step_index"] for s in after] == list(range(total))  # nothing lost, nothing twice
    assert all(s["ok"] for s in after), [s["error"] for s in after if not s["ok"]]
    for index, sample in before.items():  # the committed samples are exactly what the killed process wrote
        assert after[index] == sample
    with sqlite3.connect(runs / "runs.sqlite") as conn:
        results = json.loads(conn.execute("SELECT results FROM runs").fetchone()[0])
        kinds = [row[0] for row in conn.execute("SELECT kind FROM events")]
    assert "lease_taken_over" in kinds  # the dead process's lease, judged stale
    cells = sorted((runs / "sim").iterdir())
    assert len(cells) == 2 and (first_cell / "truth.jsonl").read_bytes()[: len(truth_before)] == truth_before
    (second_cell,) = [cell for cell in cells if cell != first_cell]
    sessions = [yaml.safe_load((cell / "station.yaml").read_text())["simulation"]["session"]
                for cell in (first_cell, second_cell)]
    assert sessions == [0, 1]  # the resumed cell: the same seed, its own noise
    # The kind measures at rest: neither cell sampled the robot's dense truth (``measures_in_motion``).
    assert not any(path.is_file() for cell in cells for path in (cell / "trajectories").glob("*"))

    # The truth of every sample, before and after the crash, reaches the results.
    if name == "iso9283_repeatability":
        for point in results["order"]:
            entry = results["points"][point]
            assert entry["n"] == 2 and entry["true_stats"]["n"] == 2, entry.keys()
    else:
        rows = [row for component in results["data"].values() for row in component]
        assert len(rows) == total and all("true" in row for row in rows)
    if name == "displacement_calibration":  # one group of 10 steps, killed after 2 to 8 of them
        assert "datum" in kinds
        # A group cut in half: its second half was measured under a re-established datum, which the
        # analysis joins to the first (to a few µm; the robot put ~10 µm between them).
        first = [r["reference"] - r["true"] for r in rows if r.get("datum", 0) == 0]
        second = [r["reference"] - r["true"] for r in rows if r.get("datum", 0) == 1]
        assert second and abs(np.mean(second) - np.mean(first)) < 3e-6
