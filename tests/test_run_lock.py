"""Exclusivity: one process per run (a lease in the store), compare-and-set states, run ids matched
exactly or by a unique prefix (never a wildcard), one folder per simulated cell."""

from __future__ import annotations

import os
import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from procedures.cli import cell_directory, main
from procedures.engine import open_engine
from procedures.station import RunLocked, StateConflict
from procedures.store import RunState, RunStore
from tests.fakes import FakeCell, FakeScience, write_station

ROOT = Path(__file__).resolve().parents[1]


def _new_run(store: RunStore) -> str:
    return store.create_run(procedure="iso9283_repeatability", parameters={}, station={}, software_version="t")


def _dead_pid() -> int:
    """The pid of a process that has ended (ours, started and reaped here)."""
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait(30)
    return child.pid


def test_a_second_lease_is_refused_while_the_holder_lives(tmp_path):
    with RunStore(tmp_path) as store:
        run_id = _new_run(store)
        lease = store.acquire_lease(run_id)
        with pytest.raises(RunLocked) as refused:
            store.acquire_lease(run_id)
        message = str(refused.value)
        assert "\n" not in message and f"pid {os.getpid()} on {socket.gethostname()}" in message
        store.release_lease(lease)
        store.release_lease(store.acquire_lease(run_id))  # free again once released


def test_a_stale_lease_of_a_dead_process_is_taken_over(tmp_path):
    with RunStore(tmp_path) as store:
        run_id = _new_run(store)
        pid = _dead_pid()
        store._db.execute("INSERT INTO leases VALUES (?, 'old', ?, ?, NULL, ?, ?)",
                          (run_id, socket.gethostname(), pid, time.time(), time.time()))
        assert store.lease_holder(run_id) is None
        lease = store.acquire_lease(run_id)
        assert lease.taken_over is not None and lease.taken_over["pid"] == pid
        assert any(e["kind"] == "lease_taken_over" and f"pid {pid}" in e["message"] for e in store.events(run_id))


def test_a_lease_from_another_host_is_stale_only_when_not_renewed(tmp_path):
    with RunStore(tmp_path) as store:
        run_id = _new_run(store)
        store._db.execute("INSERT INTO leases VALUES (?, 'far', 'other-host', 1, NULL, ?, ?)",
                          (run_id, time.time(), time.time()))
        with pytest.raises(RunLocked, match="other-host"):
            store.acquire_lease(run_id)
        store._db.execute("UPDATE leases SET renewed = ? WHERE run_id = ?", (time.time() - 3600, run_id))
        assert store.acquire_lease(run_id).taken_over["host"] == "other-host"


def test_state_changes_are_compare_and_set_on_the_state_and_the_lease(tmp_path):
    with RunStore(tmp_path) as store:
        run_id = _new_run(store)
        lease = store.acquire_lease(run_id)
        store.set_state(run_id, RunState.RUNNING, expected=RunState.QUEUED, lease=lease)
        with pytest.raises(StateConflict, match="it is RUNNING"):
            store.set_state(run_id, RunState.FINISHED, expected=RunState.PAUSED, lease=lease)
        # Another process took the lease over (it judged ours stale): we may no longer write the state.
        store._db.execute("UPDATE leases SET token = 'theirs' WHERE run_id = ?", (run_id,))
        with pytest.raises(StateConflict, match="no longer holds the run's lease"):
            store.set_state(run_id, RunState.FAILED, expected=RunState.RUNNING, lease=lease)
        assert store.get_run(run_id)["state"] == RunState.RUNNING


def test_run_ids_match_exactly_or_by_unique_prefix_never_as_a_pattern(tmp_path):
    with RunStore(tmp_path) as store:
        first, second = _new_run(store), _new_run(store)
        assert store.get_run(first)["id"] == first
        assert store.get_run(second[:8])["id"] == second
        for pattern in ("%", "_", first[:4] + "%", "_" * 32, "*", ""):
            with pytest.raises(KeyError):
                store.get_run(pattern)
        ids = [first, second]
        while len({run_id[0] for run_id in ids}) == len(ids):  # until two ids share their first digit
            ids.append(_new_run(store))
        shared = next(run_id[0] for run_id in ids if sum(other[0] == run_id[0] for other in ids) > 1)
        with pytest.raises(KeyError, match="ambiguous"):
            store.get_run(shared)


def test_every_simulated_cell_gets_its_own_folder(tmp_path):
    folders = {cell_directory(tmp_path) for _ in range(5)}  # five in the same second
    assert len(folders) == 5 and all(folder.parent == tmp_path / "sim" for folder in folders)


def _committed(db: Path) -> int:
    if not db.exists():
        return 0
    with sqlite3.connect(db, timeout=10) as conn:
        try:
            return conn.execute("SELECT COUNT(*) FROM samples").fetchone()[0]
        except sqlite3.OperationalError:
            return 0


def test_a_second_resume_of_a_running_run_is_refused_in_one_line(tmp_path):
    station = write_station(tmp_path / "station.yaml")
    procedure = tmp_path / "iso.yaml"
    procedure.write_text("procedure: iso9283_repeatability\n"
                         "parameters: {cycles: 30, settle_time_s: 0, frames_per_pose: 1}\n")
    runs = tmp_path / "runs"
    # 155 steps of 0.3 s: the holder is still running whatever the load; it is killed once checked.
    holder = subprocess.Popen(
        [sys.executable, "-m", "tests.fakes", str(runs), str(station), str(procedure), "--move-delay", "0.3"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        deadline = time.monotonic() + 60
        while _committed(runs / "runs.sqlite") < 2:
            assert holder.poll() is None, holder.stderr.read()
            assert time.monotonic() < deadline
            time.sleep(0.02)
        run_id = holder.stdout.readline().strip()
        # The CLI refuses before it starts anything ...
        second = subprocess.run([sys.executable, "-m", "procedures.cli", "resume", run_id[:10], "--runs-dir",
                                 str(runs)], cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert second.returncode == 1
        assert second.stderr.strip().count("\n") == 0 and f"already being run by pid {holder.pid}" in second.stderr
        # ... and so does the API, before it touches a device.
        cell = FakeCell(seed=1)
        with pytest.raises(RunLocked):
            with open_engine(runs, run_id=run_id, science=FakeScience(cell), devices=cell.devices(),
                             operator=cell.operator):
                pass
        assert cell.moves == 0
        assert holder.poll() is None, "the holder ended before the checks: they proved nothing"
    finally:
        holder.kill()  # our own child, by its handle
        holder.communicate()
    with RunStore(runs) as store:
        assert store.get_run(run_id)["state"] == RunState.RUNNING  # the refused processes changed nothing
        done = [s.step_index for s in store.samples(run_id)]
        assert done == list(range(len(done)))
        assert store.lease_holder(run_id) is None  # its holder is dead: the next resume takes it over


def test_resume_of_an_unknown_or_pattern_id_is_one_line(tmp_path, capsys):
    with RunStore(tmp_path) as store:
        _new_run(store)
    assert main(["resume", "%", "--runs-dir", str(tmp_path)]) == 1
    assert capsys.readouterr().err.strip() == f"no run '%' in {tmp_path / 'runs.sqlite'}"
