"""The run-related CLI subcommands, on a store filled by a fake run."""

import json
import textwrap

import pytest

from procedures.cli import main
from procedures.engine import open_engine
from tests.fakes import FakeCell, FakeScience, write_station


@pytest.fixture(scope="module")
def runs_dir(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("cli")
    station = write_station(tmp_path / "station.yaml")
    cell = FakeCell(seed=9)
    proc = tmp_path / "iso.yaml"
    proc.write_text("procedure: iso9283_repeatability\nparameters: {cycles: 3, settle_time_s: 0, frames_per_pose: 1}\n")
    with open_engine(tmp_path / "runs", procedure=proc, station=station, science=FakeScience(cell),
                     devices=cell.devices(), operator=cell.operator) as engine:
        engine.execute()
        run_id = engine.run_id
    return tmp_path / "runs", run_id


def test_validate_ok_and_bad(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text(textwrap.dedent("""\
        procedure: iso9283_repeatability
        parameters:
          cycles: thirty
        """))
    assert main(["validate", str(bad)]) == 1
    err = capsys.readouterr().err
    assert f"{bad}:3: parameters.cycles: input should be a valid integer" in err
    station = write_station(tmp_path / "station.yaml")
    text = station.read_text().replace("max_speed: 0.5", "max_speed: -1")
    station.write_text(text)
    line = text.splitlines().index("  max_speed: -1") + 1
    assert main(["validate", str(station)]) == 1
    assert f"{station}:{line}: envelope.max_speed: input should be greater than 0" in capsys.readouterr().err


def test_validate_shipped_procedures(capsys):
    from procedures.engine import PACKAGE_DIR

    files = [str(PACKAGE_DIR / f"{n}.yaml") for n in ("displacement_calibration", "angle_calibration",
                                                       "iso9283_repeatability")]
    assert main(["validate", *files]) == 0
    assert capsys.readouterr().out.count(": OK (") == 3


def test_runs_and_show(runs_dir, capsys):
    runs, run_id = runs_dir
    assert main(["runs", "--runs-dir", str(runs)]) == 0
    out = capsys.readouterr().out
    assert run_id[:12] in out and "FINISHED" in out and "20/20" in out
    assert main(["runs", "--runs-dir", str(runs), "--json"]) == 0
    assert json.loads(capsys.readouterr().out.splitlines()[0])["id"] == run_id
    assert main(["show", run_id[:8], "--runs-dir", str(runs)]) == 0
    out = capsys.readouterr().out
    assert "RP_l (µm)" in out and "P5" in out and "20 ok, 0 failed" in out
    assert main(["show", "nosuchrun", "--runs-dir", str(runs)]) == 1


def test_export_and_report(runs_dir, tmp_path, capsys):
    runs, run_id = runs_dir
    assert main(["export", run_id, "--csv", "--runs-dir", str(runs)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("run_id,step_index") and len(lines) == 21
    out = tmp_path / "run.json"
    assert main(["export", run_id, "--json", "-o", str(out), "--runs-dir", str(runs)]) == 0
    assert len(json.loads(out.read_text())["samples"]) == 20
    assert main(["report", run_id, "--runs-dir", str(runs)]) == 0
    path = capsys.readouterr().out.strip()
    assert path.endswith("report.html") and "ISO 9283" in open(path, encoding="utf-8").read()


def test_missing_store_is_a_clear_message(tmp_path, capsys):
    assert main(["runs", "--runs-dir", str(tmp_path / "none")]) == 1
    assert capsys.readouterr().err.startswith("no run store in")


def test_a_run_is_titled_by_the_parameters_in_force(tmp_path, capsys):
    """The built-in file is named "..., 30 cycles"; a run of it with ``--set cycles=3`` is titled "3 cycles" by
    show, the web view's list and live page (and so OPC UA's Title), never by the file's name."""
    from procedures.serve import StoreReader

    station = write_station(tmp_path / "station.yaml")
    cell = FakeCell(seed=4)
    with open_engine(tmp_path / "runs", procedure="iso9283_repeatability", station=station,
                     science=FakeScience(cell), devices=cell.devices(), operator=cell.operator,
                     overrides=["cycles=3", "settle_time_s=0", "frames_per_pose=1"]) as engine:
        assert engine.procedure.name == "ISO 9283 pose repeatability, 30 cycles"
        engine.execute()
        run_id = engine.run_id
    assert main(["show", run_id, "--runs-dir", str(tmp_path / "runs")]) == 0
    shown = capsys.readouterr().out.splitlines()
    assert shown[1] == "title      ISO 9283 pose repeatability and accuracy — 3 cycles"
    reader = StoreReader(tmp_path / "runs")
    try:
        assert [r["title"] for r in reader.runs()] == ["ISO 9283 pose repeatability and accuracy — 3 cycles planned"]
        assert reader.snapshot(run_id)["run"]["title"] == "ISO 9283 pose repeatability and accuracy — 3 cycles"
    finally:
        reader.close()
