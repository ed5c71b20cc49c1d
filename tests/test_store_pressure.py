"""The store under pressure (issue 28, item 4): a full disk, another process's write lock, a damaged file
and a read-only runs folder, each real (SQLite's own page limit, a second process in ``BEGIN EXCLUSIVE``,
bytes overwritten in a real store file, ``chattr +i`` or ``chmod``), on the fake cell.

A run the store fails under pauses with one line (where, why, what to do), robot and table stopped first;
a command says one line, never an internal error; nothing committed is lost; the reading commands work on
a store that can only be read.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from procedures.cli import main
from procedures.engine import open_engine
from procedures.station import RunError
from procedures.store import RunState, RunStore
from tests.fakes import FakeCell, FakeScience, write_station

SERIAL = "20235500123"  # the fake robot's
HOLD_LOCK = """
import sqlite3, sys, time
db = sqlite3.connect(sys.argv[1], isolation_level=None, timeout=10)
db.execute("BEGIN EXCLUSIVE")
print("locked", flush=True)
time.sleep(float(sys.argv[2]))
db.execute("COMMIT")
"""


def _procedure(tmp_path: Path, **params) -> Path:
    body = ", ".join(f"{k}: {v}" for k, v in {"settle_time_s": 0, "frames_per_pose": 1, **params}.items())
    path = tmp_path / "iso.yaml"
    path.write_text(f"procedure: iso9283_repeatability\nparameters: {{{body}}}\n")
    return path


@pytest.fixture
def cell_setup(tmp_path, monkeypatch):
    monkeypatch.setenv("INSTRUMENT_STORE_TIMEOUT", "0.5")
    monkeypatch.delenv("INSTRUMENT_SQLITE_MAX_PAGES", raising=False)
    monkeypatch.delenv("INSTRUMENT_STORE", raising=False)
    truth = tmp_path / "truth.jsonl"
    station = write_station(tmp_path / "station.yaml", truth_log=str(truth))
    return tmp_path, station, FakeCell(seed=3, truth_log=truth)


def _engine(tmp_path, station, cell, procedure=None, run_id=None, **kwargs):
    return open_engine(tmp_path / "runs", procedure=procedure, station=station, run_id=run_id,
                       science=FakeScience(cell), devices=cell.devices(), operator=cell.operator, **kwargs)


@pytest.fixture
def lock_holder():
    """A second process that holds the store's write lock (``BEGIN EXCLUSIVE``) for ``hold_s``; stopped at the end."""
    started: list[subprocess.Popen] = []

    def start(db: Path, hold_s: float) -> subprocess.Popen:
        process = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(db), str(hold_s)],
                                   stdout=subprocess.PIPE, text=True)
        started.append(process)
        assert process.stdout is not None and process.stdout.readline().strip() == "locked"
        return process

    yield start
    for process in started:
        if process.poll() is None:
            process.kill()
        process.wait(10)
        if process.stdout is not None:
            process.stdout.close()


def _stored(store: RunStore, run_id: str) -> dict[int, tuple]:
    return {s.step_index: (s.ok, s.t_start, s.t_measured, None if s.solved is None else tuple(s.solved.pose))
            for s in store.samples(run_id)}


def _one_line(capsys) -> tuple[str, str]:
    out, err = capsys.readouterr()
    assert "internal error" not in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1, err
    return out, err.strip()


# ------------------------------------------------------------------------------------------ disk full
def test_a_full_disk_mid_run_pauses_it_with_one_line_and_the_robot_stopped(cell_setup, monkeypatch):
    tmp_path, station, cell = cell_setup
    runs = tmp_path / "runs"
    RunStore(runs).close()  # the empty store: its size, to give the run's connection a page limit above it
    with sqlite3.connect(runs / "runs.sqlite") as probe:
        pages, page_size = (probe.execute(f"PRAGMA {name}").fetchone()[0] for name in ("page_count", "page_size"))
    limit = pages + 400
    monkeypatch.setenv("INSTRUMENT_SQLITE_MAX_PAGES", str(limit))
    before: dict[int, tuple] = {}

    def fill_the_disk(event):  # another writer takes the rest of the room, as a full disk would
        if event["event"] == "progress" and event["done"] == 4:
            before.update(_stored(engine.store, engine.run_id))
            with sqlite3.connect(runs / "runs.sqlite") as other:
                other.execute("CREATE TABLE filler (b BLOB)")
                size = other.execute("PRAGMA page_count").fetchone()[0]
                other.execute("INSERT INTO filler VALUES (zeroblob(?))", ((limit - size + 5) * page_size,))

    stops_before = cell.robot.stops
    with _engine(tmp_path, station, cell, _procedure(tmp_path, cycles=3), listener=fill_the_disk) as engine:
        assert engine.execute() == RunState.PAUSED
        run = engine.store.get_run(engine.run_id)
        after = _stored(engine.store, engine.run_id)
    assert cell.robot.stops > stops_before  # stopped explicitly, before the state was stored
    reason = run["reason"]
    assert reason.startswith(f"store: disk full at {runs / 'runs.sqlite'} (") and "MB free" in reason
    assert f"free space, then: instrument resume {run['id']}" in reason and "\n" not in reason
    assert len(before) == 4 and {k: after[k] for k in before} == before  # nothing committed lost or changed

    # Space freed: the resume measures the rest, and the first samples are still the same.
    monkeypatch.delenv("INSTRUMENT_SQLITE_MAX_PAGES")
    with sqlite3.connect(runs / "runs.sqlite") as other:
        other.execute("DROP TABLE filler")
    with _engine(tmp_path, station, cell, run_id=run["id"]) as engine:
        assert engine.execute() == RunState.FINISHED
        final = _stored(engine.store, engine.run_id)
        assert len(final) == engine.store.get_run(run["id"])["total_steps"]
    assert {k: final[k] for k in before} == before


def test_the_cli_ends_a_run_on_a_full_disk_paused_with_exit_status_3(cell_setup, monkeypatch, capsys):
    import argparse

    from procedures.cli import drive

    tmp_path, station, cell = cell_setup
    runs = tmp_path / "runs"
    RunStore(runs).close()
    with sqlite3.connect(runs / "runs.sqlite") as probe:
        pages, page_size = (probe.execute(f"PRAGMA {name}").fetchone()[0] for name in ("page_count", "page_size"))
    monkeypatch.setenv("INSTRUMENT_SQLITE_MAX_PAGES", str(pages + 400))

    def fill(event):
        if event["event"] == "progress" and event["done"] == 2:
            with sqlite3.connect(runs / "runs.sqlite") as other:
                other.execute("CREATE TABLE filler (b BLOB)")
                size = other.execute("PRAGMA page_count").fetchone()[0]
                other.execute("INSERT INTO filler VALUES (zeroblob(?))", ((pages + 400 - size + 5) * page_size,))

    with _engine(tmp_path, station, cell, _procedure(tmp_path, cycles=2), listener=fill) as engine:
        status = drive(engine, argparse.Namespace(quiet=False, jsonl=False, runs_dir=str(runs), store=None))
    out, err = capsys.readouterr()
    assert status == 3
    assert "internal error" not in out + err and "Traceback" not in out + err
    assert f"run {engine.run_id}: PAUSED after" in out and "store: disk full at" in out


@pytest.fixture
def tiny_disk(tmp_path):
    """A real 16 MB tmpfs (needs root and a kernel that lets it mount), unmounted at the end."""
    mount_point = tmp_path / "disk"
    mount_point.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=16m", "tmpfs", str(mount_point)],
                             capture_output=True, text=True) if shutil.which("mount") else None
    if mounted is None or mounted.returncode != 0:
        pytest.skip("a tmpfs cannot be mounted here (not root, or not allowed): the page-limit tests cover it")
    yield mount_point
    subprocess.run(["umount", "-l", str(mount_point)], capture_output=True)


def test_a_really_full_disk_mid_run_pauses_it_and_the_resume_finishes(cell_setup, tiny_disk):
    tmp_path, station, cell = cell_setup
    filler = tiny_disk / "filler"
    before: dict[int, tuple] = {}

    def fill_the_disk(event):  # another program takes every byte that is left
        if event["event"] == "progress" and event["done"] == 3 and not filler.exists():
            before.update(_stored(engine.store, engine.run_id))
            with open(filler, "wb") as handle:
                try:
                    while True:
                        handle.write(bytes(64 * 1024))
                        handle.flush()
                except OSError:
                    pass

    stops_before = cell.robot.stops
    with open_engine(tiny_disk / "runs", procedure=_procedure(tmp_path, cycles=2), station=station,
                     science=FakeScience(cell), devices=cell.devices(), operator=cell.operator,
                     listener=fill_the_disk) as engine:
        assert engine.execute() == RunState.PAUSED
        run = engine.store.get_run(engine.run_id)
        assert {k: v for k, v in _stored(engine.store, engine.run_id).items() if k in before} == before
    assert cell.robot.stops > stops_before
    assert run["reason"].startswith(f"store: disk full at {tiny_disk / 'runs' / 'runs.sqlite'} ("), run["reason"]
    assert f"free space, then: instrument resume {run['id']}" in run["reason"]
    filler.unlink()
    with open_engine(tiny_disk / "runs", run_id=run["id"], station=station, science=FakeScience(cell),
                     devices=cell.devices(), operator=cell.operator) as engine:
        assert engine.execute() == RunState.FINISHED
        assert len(engine.store.samples(run["id"])) == run["total_steps"]


# ------------------------------------------------------------------------------------------- locked
def test_a_store_locked_mid_run_pauses_once_the_lock_is_gone_naming_the_holder(cell_setup, lock_holder):
    tmp_path, station, cell = cell_setup
    holder: list[subprocess.Popen] = []

    def lock(event):
        if event["event"] == "progress" and event["done"] == 3 and not holder:
            holder.append(lock_holder(tmp_path / "runs" / "runs.sqlite", 1.2))

    stops_before = cell.robot.stops
    with _engine(tmp_path, station, cell, _procedure(tmp_path, cycles=2), listener=lock) as engine:
        assert engine.execute() == RunState.PAUSED
        run = engine.store.get_run(engine.run_id)
        assert len(engine.store.samples(engine.run_id)) == 3
    assert cell.robot.stops > stops_before
    assert run["reason"].startswith(f"store locked by another process (pid {holder[0].pid}) for longer than 0.5 s")
    assert f"instrument resume {run['id']}" in run["reason"]
    with _engine(tmp_path, station, cell, run_id=run["id"]) as engine:  # lock gone: it finishes
        assert engine.execute() == RunState.FINISHED


def test_a_lock_that_outlasts_the_pause_says_so_in_one_line(cell_setup, lock_holder):
    tmp_path, station, cell = cell_setup
    holder: list[subprocess.Popen] = []

    def lock(event):
        if event["event"] == "progress" and event["done"] == 2 and not holder:
            holder.append(lock_holder(tmp_path / "runs" / "runs.sqlite", 60))

    stops_before = cell.robot.stops
    with _engine(tmp_path, station, cell, _procedure(tmp_path, cycles=2), listener=lock) as engine:
        with pytest.raises(RunError) as caught:  # procedures.store.StoreTrouble
            engine.execute()
    message = str(caught.value)
    assert "\n" not in message and f"pid {holder[0].pid}" in message and "could not be marked PAUSED" in message
    assert cell.robot.stops > stops_before


def test_a_locked_store_before_the_start_is_one_line_and_reading_still_works(cell_setup, lock_holder, capsys):
    tmp_path, station, cell = cell_setup
    runs = tmp_path / "runs"
    with _engine(tmp_path, station, cell, _procedure(tmp_path, cycles=2), pause_handler=lambda e: "detach") as engine:
        engine.request_pause()
        assert engine.execute() == RunState.PAUSED
        run_id = engine.run_id
    holder = lock_holder(runs / "runs.sqlite", 60)
    with pytest.raises(RunError, match=f"^store locked by another process \\(pid {holder.pid}\\)"):
        with _engine(tmp_path, station, cell, _procedure(tmp_path, cycles=2)):
            pass
    assert main(["resume", run_id, "--runs-dir", str(runs)]) == 1
    _, err = _one_line(capsys)
    assert err.startswith(f"store locked by another process (pid {holder.pid})")
    assert main(["runs", "--runs-dir", str(runs)]) == 0  # WAL: reading is not held up by a writer
    assert run_id[:8] in capsys.readouterr().out


# ------------------------------------------------------------------------------------------ damaged
@pytest.fixture
def finished_run(cell_setup):
    tmp_path, station, cell = cell_setup
    with _engine(tmp_path, station, cell, _procedure(tmp_path, cycles=2)) as engine:
        assert engine.execute() == RunState.FINISHED
        run_id = engine.run_id
    return tmp_path / "runs", run_id


@pytest.mark.parametrize("where", ["pages", "header"])
def test_a_damaged_store_is_one_line_with_the_way_to_recover_it_for_every_command(finished_run, capsys, where):
    runs, run_id = finished_run
    path = runs / "runs.sqlite"
    assert not path.with_name("runs.sqlite-wal").exists()  # all of it in the file, checkpointed
    data = bytearray(path.read_bytes())
    if where == "header":
        data[:16] = b"not a database!!"
    else:
        data[4096:] = b"\xff" * (len(data) - 4096)
    path.write_bytes(bytes(data))
    commands = [["runs"], ["show", run_id], ["report", run_id], ["history", "--robot", SERIAL],
                ["export", run_id, "--csv"], ["resume", run_id]]
    for command in commands:
        assert main([*command, "--runs-dir", str(runs)]) == 1, command
        _, err = _one_line(capsys)
        assert err.startswith(f"store damaged: {path}"), (command, err)
        assert ".recover" in err and "move the damaged file aside" in err
    with pytest.raises(RunError, match="^store damaged: "):  # procedures.store.StoreDamaged
        RunStore(runs)
    # The real command, in its own process: the same line, exit status 1, nothing else.
    process = subprocess.run([sys.executable, "-m", "procedures.cli", "runs", "--runs-dir", str(runs)],
                             capture_output=True, text=True, timeout=60)
    assert process.returncode == 1 and process.stdout == ""
    assert process.stderr.startswith(f"store damaged: {path}") and len(process.stderr.splitlines()) == 1


# ---------------------------------------------------------------------------------------- read-only
@pytest.fixture
def read_only(finished_run):
    """The runs folder and its store made unwritable for this process: ``chattr +i`` as root (root ignores
    permissions), ``chmod`` otherwise; undone at the end."""
    runs, run_id = finished_run
    paths = [runs, runs / "runs.sqlite"]
    if os.geteuid() == 0:
        chattr = shutil.which("chattr")
        if chattr is None or subprocess.run([chattr, "+i", *map(str, paths)], capture_output=True).returncode:
            subprocess.run([chattr or "true", "-i", *map(str, paths)], capture_output=True)
            pytest.skip("running as root and chattr +i is not available here: cannot make a folder read-only")
        undo = [chattr, "-i", *map(str, paths)]
    else:
        modes = [p.stat().st_mode for p in paths]
        for p in reversed(paths):
            p.chmod(0o444 if p.is_file() else 0o555)
    assert not os.access(runs, os.W_OK)
    yield runs, run_id
    if os.geteuid() == 0:
        subprocess.run(undo, check=True)
    else:
        for p, mode in zip(paths, modes):
            p.chmod(mode)


def test_reading_commands_work_on_a_read_only_store_and_writing_ones_say_it_is_read_only(
        read_only, cell_setup, capsys):
    runs, run_id = read_only
    tmp_path, station, _ = cell_setup
    assert main(["runs", "--runs-dir", str(runs)]) == 0
    assert run_id[:8] in capsys.readouterr().out
    assert main(["show", run_id, "--runs-dir", str(runs)]) == 0
    assert "FINISHED" in capsys.readouterr().out
    assert main(["history", "--robot", SERIAL, "--runs-dir", str(runs)]) == 0
    assert "P1" in capsys.readouterr().out
    report = tmp_path / "elsewhere.html"
    assert main(["report", run_id, "--runs-dir", str(runs), "-o", str(report)]) == 0
    assert report.stat().st_size > 1000
    capsys.readouterr()
    assert main(["report", run_id, "--runs-dir", str(runs)]) == 1
    _, err = _one_line(capsys)
    assert err.startswith("store is read-only:") and "-o FILE" in err
    for command in (["resume", run_id], ["run", "iso9283_repeatability", "--station", str(station)]):
        assert main([*command, "--runs-dir", str(runs)]) == 1, command
        _, err = _one_line(capsys)
        assert err.startswith(f"store is read-only: {runs / 'runs.sqlite'}"), (command, err)
    assert not (runs / "runs.sqlite-wal").exists()  # nothing was written
