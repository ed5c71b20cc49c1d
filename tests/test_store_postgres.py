"""The run store on a real PostgreSQL server (started by the fixture): the same behaviour as on SQLite.

Schema versions, samples and their primary key, the lease and compare-and-set states (with
PostgreSQL's locks), the change counter a reader polls, a whole engine run that records the robot's
identity, and the CLI reading it all back with ``--store``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from procedures.cli import main
from procedures.engine import open_engine
from procedures.station import RunLocked, StateConflict
from procedures.store import LATEST, DuplicateStep, RunState, RunStore, Sample, SolvedPose, StoreError
from tests._postgres import postgres_server
from tests.fakes import FakeCell, FakeScience, write_station

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def server():
    with postgres_server() as running:
        yield running


@pytest.fixture
def url(server) -> str:
    return server.new_database()


def _new_run(store: RunStore, procedure: str = "iso9283_repeatability") -> str:
    return store.create_run(procedure=procedure, parameters={}, station={}, software_version="test")


def test_schema_is_versioned_and_migrated_once(url, tmp_path):
    with RunStore(tmp_path, url=url) as store:
        assert store.dialect == "postgresql" and "postgresql://" in store.location
        versions = [row["version"] for row in store._db.rows("SELECT version FROM schema_version ORDER BY version")]
        assert versions == list(range(1, LATEST + 1))
    with RunStore(tmp_path, url=url) as store:  # opened again: nothing applied twice
        assert len(store._db.rows("SELECT version FROM schema_version")) == LATEST
        store._db.execute("INSERT INTO schema_version (version, applied) VALUES (?, ?)", (LATEST + 1, time.time()))
    with pytest.raises(StoreError, match=f"schema version {LATEST + 1} is newer than this software"):
        RunStore(tmp_path, url=url)
    assert not (tmp_path / "runs.sqlite").exists()  # the database is the server's; the folder keeps files only


def test_samples_events_and_prefixes_as_on_sqlite(url, tmp_path):
    with RunStore(tmp_path, url=url) as store:
        run_id = _new_run(store)
        store.add_sample(Sample(run_id, 0, "iso/c000/P1", "iso", ok=False, error="no cross"))
        store.add_sample(Sample(run_id, 0, "iso/c000/P1", "iso",
                                solved=SolvedPose(pose=(0.001, float("nan")))))  # measured again
        with pytest.raises(DuplicateStep):
            store.add_sample(Sample(run_id, 0, "iso/c000/P1", "iso"))
        (sample,) = store.samples(run_id)
        assert sample.ok and sample.solved.pose[0] == 0.001 and sample.solved.pose[1] != sample.solved.pose[1]
        assert [s.error for s in store.superseded_samples(run_id)] == ["no cross"]
        assert store.measured_steps(run_id) == store.committed_steps(run_id) == {0}
        for number in range(30):
            store.log(run_id, "note", str(number))
        assert [e["message"] for e in store.events(run_id) if e["kind"] == "note"] == [str(n) for n in range(30)]
        assert store.get_run(run_id[:7])["id"] == run_id
        with pytest.raises(KeyError):
            store.get_run("%")  # a prefix is plain text, never a pattern
        store.update_run(run_id, robot_serial="SN-1", robot_model="UR5")
        assert [r["id"] for r in store.list_runs(robot="SN-1")] == [run_id]
        assert store.robots()[0]["serial"] == "SN-1"


_TRY_LEASE = """
import sys
from procedures.station import RunLocked
from procedures.store import RunStore
with RunStore(sys.argv[1], url=sys.argv[2]) as store:
    try:
        store.acquire_lease(sys.argv[3])
    except RunLocked as exc:
        print("refused:", exc)
        sys.exit(0)
    print("taken", flush=True)
    sys.stdin.read()  # hold it until the test closes our stdin
"""


def _lease_takers(tmp_path: Path, url: str, run_id: str, count: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", _TRY_LEASE, str(tmp_path), url, run_id], cwd=ROOT,
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            for _ in range(count)]


def test_one_lease_among_racing_processes_and_stale_leases_taken_over(url, tmp_path):
    with RunStore(tmp_path, url=url) as store:
        run_id = _new_run(store)
    takers = _lease_takers(tmp_path, url, run_id, 4)
    try:
        lines = []
        for taker in takers:
            line = taker.stdout.readline()
            if line.startswith("refused"):
                taker.wait(30)
            lines.append(line)
        assert sum(line.startswith("taken") for line in lines) == 1, lines
        assert sum(line.startswith("refused:") and "already being run by pid" in line for line in lines) == 3
        with RunStore(tmp_path, url=url) as store, pytest.raises(RunLocked):
            store.acquire_lease(run_id)
    finally:
        for taker in takers:
            if taker.poll() is None:
                taker.stdin.close()  # the holder ends
            taker.wait(30)
            for stream in (taker.stdout, taker.stderr):
                stream.close()
    with RunStore(tmp_path, url=url) as store:  # the holder's process is gone: its lease is stale
        lease = store.acquire_lease(run_id)
        assert lease.taken_over is not None
        assert "lease_taken_over" in [e["kind"] for e in store.events(run_id)]
        store._db.execute("UPDATE leases SET host = 'other-host', renewed = ? WHERE run_id = ?", (time.time(), run_id))
        with pytest.raises(RunLocked):  # another host's lease, renewed just now
            store.acquire_lease(run_id)
        store._db.execute("UPDATE leases SET renewed = ? WHERE run_id = ?", (time.time() - 3600, run_id))
        assert store.acquire_lease(run_id).taken_over["host"] == "other-host"  # not renewed for an hour


def test_state_changes_are_compare_and_set_on_state_and_lease(url, tmp_path):
    with RunStore(tmp_path, url=url) as store:
        run_id = _new_run(store)
        lease = store.acquire_lease(run_id)
        store.set_state(run_id, RunState.RUNNING, expected=RunState.QUEUED, lease=lease)
        with pytest.raises(StateConflict, match="it is RUNNING"):
            store.set_state(run_id, RunState.PAUSED, expected=RunState.QUEUED, lease=lease)
        store._db.execute("UPDATE leases SET token = 'theirs' WHERE run_id = ?", (run_id,))
        with pytest.raises(StateConflict, match="no longer holds the run's lease"):
            store.set_state(run_id, RunState.FINISHED, expected=RunState.RUNNING, lease=lease)
        assert store.get_run(run_id)["state"] == RunState.RUNNING


def test_the_change_counter_moves_with_other_connections_commits_only(url, tmp_path):
    with RunStore(tmp_path, url=url) as reader, RunStore(tmp_path, url=url) as writer:
        before = reader.version()
        assert reader.version() == before  # reading changes nothing
        reader.list_runs()
        assert reader.version() == before
        run_id = _new_run(writer)
        after_create = reader.version()
        assert after_create != before
        writer.add_sample(Sample(run_id, 0, "k", "iso"))
        assert reader.version() != after_create


def test_an_engine_run_on_postgres_records_the_robot_and_the_cli_reads_it(url, tmp_path, capsys):
    station = write_station(tmp_path / "station.yaml")
    procedure = tmp_path / "iso.yaml"
    procedure.write_text("procedure: iso9283_repeatability\nparameters: {cycles: 2, settle_time_s: 0, "
                         "frames_per_pose: 1}\n")
    runs = tmp_path / "runs"
    cell = FakeCell(seed=4)
    with open_engine(runs, procedure=procedure, station=station, science=FakeScience(cell), devices=cell.devices(),
                     operator=cell.operator, store=url, overrides=["cycles=3"]) as engine:
        assert engine.execute() == RunState.FINISHED
        run_id = engine.run_id
    assert not (runs / "runs.sqlite").exists()
    with RunStore(runs, url=url) as store:
        run = store.get_run(run_id)
        (session,) = store.sessions(run_id)  # the session's test conditions: a run-level record (version 6)
    assert (run["robot_manufacturer"], run["robot_model"], run["robot_serial"], run["robot_controller_version"]) == (
        "Universal Robots", "UR5", "20235500123", "5.15.0.0")  # what the fake controller answers
    assert session.robot["serial_number"] == "20235500123"
    assert run["results"]["test_conditions"]["sessions"] == [session.to_stored()]
    assert run["parameters"]["cycles"] == 3 and "--set cycles=3" in run["procedure_text"]
    assert len(run["results"]["points"]["P1"]["stats"]) > 0

    assert main(["runs", "--runs-dir", str(runs), "--store", url, "--robot", "20235500123"]) == 0
    listing = capsys.readouterr().out.splitlines()
    assert listing[0].split()[:3] == ["RUN", "CREATED", "STATE"] and run_id[:12] in listing[1]
    assert main(["history", "--robot", "20235500123", "--runs-dir", str(runs), "--store", url, "--json"]) == 0
    history = json.loads(capsys.readouterr().out)
    assert history["serial"] == "20235500123" and history["runs"] == 1
    rp_l = history["points"]["P1"][0]["figures"]["rp_l"]
    assert rp_l["value"] == pytest.approx(run["results"]["points"]["P1"]["stats"]["rp_l"])
    assert main(["show", run_id[:8], "--runs-dir", str(runs), "--store", url]) == 0
    assert "serial 20235500123" in capsys.readouterr().out


def test_a_bad_store_url_is_one_line(tmp_path, capsys, server):
    assert main(["runs", "--runs-dir", str(tmp_path), "--store", "mysql://x/y"]) == 1
    assert capsys.readouterr().err.strip().startswith("--store: expected a postgresql://")
    secret = f"postgresql://postgres:hunter2@127.0.0.1:{server.port}/no_such_database"
    assert main(["runs", "--runs-dir", str(tmp_path), "--store", secret]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "cannot connect" in err and "hunter2" not in err and ":***@" in err


def test_the_environment_variable_names_the_store(url, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("INSTRUMENT_STORE", url)
    with RunStore(tmp_path) as store:
        run_id = _new_run(store)
    assert main(["runs", "--runs-dir", str(tmp_path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["id"] == run_id
    assert os.environ["INSTRUMENT_STORE"] == url


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_several_cells_writing_to_one_store_at_once_lose_nothing(backend, tmp_path, request):
    """Four engine processes (four cells) measure a run each into one store at the same time."""
    env = dict(os.environ)
    env.pop("INSTRUMENT_STORE", None)
    url = None
    if backend == "postgresql":
        url = request.getfixturevalue("url")
        env["INSTRUMENT_STORE"] = url  # tests.fakes opens its store as the CLI does: through the variable
    station = write_station(tmp_path / "station.yaml")
    procedure = tmp_path / "iso.yaml"
    procedure.write_text("procedure: iso9283_repeatability\nparameters: {cycles: 4, settle_time_s: 0, "
                         "frames_per_pose: 1}\n")
    runs = tmp_path / "runs"
    cells = [subprocess.Popen([sys.executable, "-m", "tests.fakes", str(runs), str(station), str(procedure),
                               "--move-delay", "0.01"], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(4)]
    outputs = []
    try:
        for cell in cells:
            out, err = cell.communicate(timeout=240)
            assert cell.returncode == 0, err[-2000:]
            outputs.append(out.split())
    finally:
        for cell in cells:
            if cell.poll() is None:
                cell.kill()
                cell.wait(10)
    assert [out[1] for out in outputs] == ["FINISHED"] * 4
    with RunStore(runs, url=url) as store:
        assert store.dialect == backend
        runs_stored = store.list_runs()
        assert sorted(r["id"] for r in runs_stored) == sorted(out[0] for out in outputs)
        for run in runs_stored:
            samples = store.samples(run["id"])
            assert [s.step_index for s in samples] == list(range(25)) and all(s.ok for s in samples)
            assert run["state"] == RunState.FINISHED and run["samples"] == 25
            assert not store.superseded_samples(run["id"])
            states = [e["message"] for e in store.events(run["id"]) if e["kind"] == "state"]
            assert states == ["RUNNING", "FINISHED"]
            assert store.lease_holder(run["id"]) is None
