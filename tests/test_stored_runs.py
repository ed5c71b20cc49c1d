"""Runs stored by an earlier version are still listed, shown, reported, exported and resumed.

``data/runs_stored_by_5786d73.sql`` is the run store (``sqlite3`` dump) that commit 5786d73 — the
engine before procedure kinds became classes and run states an Enum — wrote for six runs on the
fake cell: a finished and a paused run of each kind. (Made with that commit's ``open_engine`` and
``tests.fakes``; its fake science gave the ISO cube from ``instrument.iso9283`` as the real one does.)

``data/runs_stored_by_410f450.sql`` is the store commit 410f450 wrote (the last before the procedures
package became subpackages and samples typed blocks): eight runs of all five kinds on the fake cell,
among them an ISO run measured in two sessions with calibration records in force, three paused runs and
two runs measured in motion (streams); ``data/runs_stored_by_410f450.outputs.json`` holds the digests of
what that commit's ``runs``, ``show``, ``report``, ``export`` and ``history`` commands and web view gave for
them (``data/make_runs_stored_by_410f450.py`` made both; ``stored_outputs.py`` takes the outputs).
"""

from __future__ import annotations

import csv
import io
import json
import math
import sqlite3
from pathlib import Path

import pytest

from procedures.cli import main
from procedures.engine import open_engine
from procedures.kinds import KINDS
from procedures.store import RunState, RunStore
from tests.fakes import FakeCell, FakeScience
from tests.stored_outputs import digest, outputs

DATA = Path(__file__).parent / "data"
FIXTURE = DATA / "runs_stored_by_5786d73.sql"
FIXTURE_410F450 = DATA / "runs_stored_by_410f450.sql"
OUTPUTS_410F450 = DATA / "runs_stored_by_410f450.outputs.json"


def _loaded(fixture: Path, runs: Path) -> Path:
    runs.mkdir()
    db = sqlite3.connect(runs / "runs.sqlite")
    db.executescript(fixture.read_text(encoding="utf-8"))
    db.close()
    return runs


@pytest.fixture
def runs_dir(tmp_path: Path) -> Path:
    return _loaded(FIXTURE, tmp_path / "runs")


@pytest.fixture
def runs_410f450(tmp_path: Path) -> Path:
    return _loaded(FIXTURE_410F450, tmp_path / "runs")


def _stored(runs_dir: Path) -> list[dict]:
    with RunStore(runs_dir) as store:
        return [store.get_run(r["id"]) for r in store.list_runs()]


def test_the_fixture_holds_a_finished_and_a_paused_run_of_each_kind(runs_dir):
    runs = _stored(runs_dir)
    assert sorted((r["procedure"], r["state"]) for r in runs) == sorted(
        (kind, state) for kind in ("displacement_calibration", "angle_calibration", "iso9283_repeatability")
        for state in (RunState.FINISHED, RunState.PAUSED))
    assert all((r["results"] is not None) == (r["state"] == RunState.FINISHED) for r in runs)


def test_stored_runs_are_listed_shown_reported_and_exported(runs_dir, tmp_path, capsys):
    runs = _stored(runs_dir)
    assert main(["runs", "--runs-dir", str(runs_dir)]) == 0
    listing = capsys.readouterr().out.splitlines()
    assert listing[0].split()[0] == "RUN"  # the header
    assert [line.split()[0] for line in listing[1:]] == [r["id"][:12] for r in runs]
    for run in runs:
        assert main(["show", run["id"], "--runs-dir", str(runs_dir)]) == 0
        shown = capsys.readouterr().out
        assert f"state      {run['state']}" in shown
        results = run["results"]
        if run["procedure"] == "iso9283_repeatability" and results:
            for label in results["order"]:
                stats = results["points"][label]["stats"]
                assert f"{stats['rp_l'] * 1e6:9.2f}" in shown and f"{stats['ap_p'] * 1e6:9.2f}" in shown
        elif results:
            assert f"record     {results['record_path']} ({results['record_id']})" in shown

        html_path = tmp_path / f"{run['id']}.html"
        assert main(["report", run["id"], "-o", str(html_path), "--runs-dir", str(runs_dir)]) == 0
        assert capsys.readouterr().out.strip() == str(html_path)
        html = html_path.read_text(encoding="utf-8")
        assert run["id"] in html and f"{run['state']} (" in html and "id=signoff" in html
        if not results:
            assert "No results: the run has not finished." in html
        elif run["procedure"] == "iso9283_repeatability":
            # stored before figure objects, uncertainty and test conditions: the ISO statistics are shown, the
            # deviations are read off the run, the conditions come from its parameters and station snapshot
            cycles = run["parameters"]["cycles"]
            assert f"— {cycles} cycles</h1>" in html and f"{cycles} cycles measured (ISO 9283 asks for 30)" in html
            assert "read off the run" in html and "stored before the test conditions were recorded" in html
            for label in results["order"]:
                stats = results["points"][label]["stats"]
                assert f"<span class=v>{stats['rp_l'] * 1e6:.2f}</span>" in html
                assert f"<span class=v>{stats['rp_a'] * 180 * 3600 / math.pi:.2f}</span>" in html  # arc-seconds
            assert html.count("class=\"circle\"") == 3 * len(results["order"])  # x–y, x–z, y–z with the RP circle
        else:
            assert results["record_id"] in html and "datum removed" in html and "error before" in html

        assert main(["export", run["id"], "--csv", "--runs-dir", str(runs_dir)]) == 0
        rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
        with RunStore(runs_dir) as store:
            samples = store.samples(run["id"])
        assert [int(row["step_index"]) for row in rows] == [s.step_index for s in samples]
        assert main(["export", run["id"], "--json", "--runs-dir", str(runs_dir)]) == 0
        assert json.loads(capsys.readouterr().out)["run"]["state"] == run["state"]


# Where each paused run stopped, and so what the operator must do when it resumes.
OPERATOR_ON_RESUME = {
    "iso9283_repeatability": [],  # the OPR stays on the robot
    "displacement_calibration": ["align y"],  # paused on the y axis: the interferometer is re-aimed there
    "angle_calibration": ["mount table:z", "mount robot"],  # paused on z: mounted there, back on the robot at the end
}


def test_paused_runs_resume_to_the_end_without_touching_committed_samples(runs_dir):
    paused = [r for r in _stored(runs_dir) if r["state"] == RunState.PAUSED]
    for number, run in enumerate(paused):
        with RunStore(runs_dir) as store:
            before = {s.step_index: s for s in store.samples(run["id"])}
        cell = FakeCell(seed=11 + number)
        with open_engine(runs_dir, run_id=run["id"][:10], science=FakeScience(cell), devices=cell.devices(),
                         operator=cell.operator) as engine:
            assert engine.execute() == RunState.FINISHED, engine.store.get_run(run["id"])["reason"]
            finished = engine.store.get_run(run["id"])
            after = engine.store.samples(run["id"])
        assert [s.step_index for s in after] == list(range(run["total_steps"]))
        for sample in after[: len(before)]:
            assert sample == before[sample.step_index]
        assert cell.log == OPERATOR_ON_RESUME[run["procedure"]]
        results = finished["results"]
        if run["procedure"] == "iso9283_repeatability":
            assert results["order"] == ["P1", "P5", "P4", "P3", "P2"]
            assert all(results["points"][p]["n"] == run["parameters"]["cycles"] for p in results["order"])
        else:
            assert Path(results["record_path"]).is_file() and finished["calibration_record_id"] == results["record_id"]


# 410f450 titled the reports of these kinds by the procedure file's name; their kinds word a title now, from
# the parameters the run had (issue 21). Their reports are compared with that title put back.
RETITLED = ("iso9283_stabilisation", "iso9283_path")


# The report of 410f450's ISO run since issue 27: its AP table has no (true) rows (the cell's true AP is not like
# for like) and its note says what "true" means per table; everything else is as before. Its digest, this version's.
TRUTH_REWORDED = {
    "report 9f3ec2a4163d4f30a80d01277a4420d1":
        "sha256:c0d5df9c2487448a5cd9c8f239adc5349d4080a90aba678de4073fb03c48164f",
}


def _as_before_compensation_groups(text: bytes, document: bytes) -> tuple[bytes, bytes]:
    """``history`` and ``history --json`` as 410f450 gave them: since issue 27 each point's table is headed by
    whether its runs were compensated (and each JSON entry says so, with the records); the figures, the flags
    and everything else are the same bytes (the fixture's robot has one compensated run)."""
    lines = text.decode().splitlines(keepends=True)
    for number, line in enumerate(lines):
        if line.startswith("P") and " — " in line:
            lines[number] = line.split(" — ")[0] + "\n"
        if line.startswith("± : "):
            lines[number] = line.replace("from the previous run of the same kind (compensated or not) by",
                                         "from the previous run by")
    history = json.loads(document)
    for entries in history["points"].values():
        for entry in entries:
            assert entry.pop("compensation") == "compensated" and len(entry.pop("records")) == 2
    return "".join(lines).encode(), (json.dumps(history) + "\n").encode()


def test_runs_stored_by_410f450_show_report_and_export_byte_for_byte(runs_410f450, tmp_path):
    """Listing, show, report, export (CSV, JSON, streams), history and the web view's run and history API give
    the very bytes commit 410f450 gave for the runs it stored (the retitled reports but for their title)."""
    expected = json.loads(OUTPUTS_410F450.read_text(encoding="utf-8"))
    produced = outputs(runs_410f450, tmp_path)
    assert sorted(produced) == sorted(expected)
    for run in _stored(runs_410f450):
        if run["procedure"] in RETITLED:
            title = KINDS[run["procedure"]].title(run["parameters"], run["results"])
            report = produced[f"report {run['id']}"]
            assert report.count(title.encode()) == 3  # <title>, <h1> and the printed pages' footer
            produced[f"report {run['id']}"] = report.replace(title.encode(), run["procedure_name"].encode())
    for run in _stored(runs_410f450):  # show's title line (issue 27): the kind's title, from the parameters in force
        shown = produced[f"show {run['id']}"].decode()
        title_line = f"title      {KINDS[run['procedure']].title(run['parameters'], run['results'])}\n"
        assert shown.splitlines(keepends=True)[1] == title_line
        produced[f"show {run['id']}"] = shown.replace(title_line, "", 1).encode()
    produced["history"], produced["history --json"] = _as_before_compensation_groups(produced["history"],
                                                                                     produced["history --json"])
    for name, reworded in TRUTH_REWORDED.items():  # see TRUTH_REWORDED
        html = produced[name].decode()
        ap_table = html[html.index("<caption>Pose accuracy AP"):].split("</table>")[0]
        assert "(true)" not in ap_table and "Pose accuracy has no true row" in html
        assert digest(produced[name]) == reworded
        produced[name] = b""
        expected[name] = digest(b"")
    differ = [name for name in expected if digest(produced[name]) != expected[name]]
    if differ:  # kept for a look: compare with the same outputs of 410f450 (data/make_runs_stored_by_410f450.py)
        kept = tmp_path / "outputs"
        kept.mkdir()
        for name in differ:
            (kept / name.replace("/", "_").replace(" ", "_")).write_bytes(produced[name])
        pytest.fail(f"{len(differ)} outputs differ from 410f450's (written to {kept}): {', '.join(differ)}")


# Where each paused run of 410f450 stopped, and so what the operator must do when it resumes.
OPERATOR_ON_RESUME_410F450 = {
    "iso9283_repeatability": [],
    "displacement_calibration": ["align x", "align z"],  # paused on x, the last of its two axes z
    "angle_calibration": ["mount table:z", "mount robot"],  # one axis, z
}


def test_runs_paused_by_410f450_resume_to_the_end(runs_410f450):
    paused = [r for r in _stored(runs_410f450) if r["state"] == RunState.PAUSED]
    assert sorted(r["procedure"] for r in paused) == sorted(OPERATOR_ON_RESUME_410F450)
    for number, run in enumerate(paused):
        with RunStore(runs_410f450) as store:
            before = store.samples(run["id"])
        cell = FakeCell(seed=31 + number)
        with open_engine(runs_410f450, run_id=run["id"], science=FakeScience(cell), devices=cell.devices(),
                         operator=cell.operator) as engine:
            assert engine.execute() == RunState.FINISHED, engine.store.get_run(run["id"])["reason"]
            finished = engine.store.get_run(run["id"])
            after = engine.store.samples(run["id"])
        assert [s.step_index for s in after] == list(range(run["total_steps"]))
        assert after[:len(before)] == before
        assert cell.log == OPERATOR_ON_RESUME_410F450[run["procedure"]]
        results = finished["results"]
        if run["procedure"] == "iso9283_repeatability":
            assert all(results["points"][p]["n"] == run["parameters"]["cycles"] for p in results["order"])
            # the session 410f450 measured (its record in its first sample) and the one that finished it
            sessions = results["test_conditions"]["sessions"]
            assert len(sessions) == 2 and sessions[0]["started"] < sessions[1]["started"]
            assert all(s["robot"]["serial_number"] == "20235500123" for s in sessions)
        else:
            assert Path(results["record_path"]).is_file() and finished["calibration_record_id"] == results["record_id"]


def _rows(db: Path, query: str) -> list[tuple]:
    with sqlite3.connect(db) as conn:
        return conn.execute(query).fetchall()


@pytest.mark.parametrize("written_by", ["5786d73", "before schema versions"])
def test_an_older_store_is_migrated_in_place_keeping_every_row(runs_dir, written_by):
    from procedures.store import LATEST, MIGRATIONS

    db = runs_dir / "runs.sqlite"
    if written_by != "5786d73":  # the store as the code just before schema versions left it: two more tables
        with sqlite3.connect(db) as conn:
            conn.executescript(MIGRATIONS[1].sqlite)
    found = 1 if written_by == "5786d73" else 2
    events = _rows(db, "SELECT rowid, run_id, time, kind, message, data FROM events ORDER BY rowid")
    samples = _rows(db, "SELECT * FROM samples ORDER BY run_id, step_index")
    runs = _rows(db, "SELECT * FROM runs ORDER BY id")
    with RunStore(runs_dir) as store:
        versions = _rows(db, "SELECT version, description FROM schema_version ORDER BY version")
        assert [v for v, _ in versions] == list(range(found, LATEST + 1))
        assert "written before schema versions" in versions[0][1]
        assert _rows(db, "SELECT id, run_id, time, kind, message, data FROM events ORDER BY id") == events
        assert _rows(db, "SELECT * FROM samples ORDER BY run_id, step_index") == samples
        assert [row[:len(runs[0])] for row in _rows(db, "SELECT * FROM runs ORDER BY id")] == runs
        assert _rows(db, "SELECT COUNT(*) FROM runs WHERE robot_serial IS NOT NULL") == [(0,)]  # older runs: NULL
        run_id = store.list_runs()[0]["id"]
        assert [e["message"] for e in store.events(run_id)] == [e[4] for e in events if e[1] == run_id]
    with RunStore(runs_dir):  # opened again: nothing applied twice
        assert len(_rows(db, "SELECT version FROM schema_version")) == LATEST - found + 1
