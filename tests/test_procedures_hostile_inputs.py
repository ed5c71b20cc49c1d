"""Hostile input to the CLI: each is refused (or survived) with one line on stderr, never a
traceback, in bounded time and memory; ``validate STATION PROCEDURE`` runs the offline dry run."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from procedures.cli import ERROR_LOG, main
from procedures.store import RunStore
from sim_devices.cell import SimCell

ROOT = Path(__file__).resolve().parents[1]
ISO = "procedure: iso9283_repeatability\n"


@pytest.fixture(scope="module")
def station(tmp_path_factory) -> Path:
    """A real station file (the simulated cell's, with its true-to-life geometry); the cell is gone
    once it is written, which validate does not mind."""
    directory = tmp_path_factory.mktemp("cell")
    with SimCell(seed=2, directory=directory / "cell") as cell:
        text = cell.station_path.read_text(encoding="utf-8")
    path = directory / "station.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def _one_line(capsys, code: int, expected_code: int = 1) -> str:
    captured = capsys.readouterr()
    assert code == expected_code, captured.err
    assert "Traceback" not in captured.err and "internal error" not in captured.err, captured.err
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    return lines[0]


def _write(path: Path, text: str | bytes) -> Path:
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8")
    return path


def _bomb(levels: int = 9) -> str:
    lines = [ISO, "a0: &a0 [x, x, x, x, x, x, x, x, x, x]\n"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]\n" for i in range(1, levels + 1)]
    return "".join(lines)


HOSTILE_PROCEDURES = [
    ("not-utf8", "caf\xe9".encode("latin-1").join([ISO.encode() + b"name: ", b"\n"]), "not UTF-8 text"),
    ("procedure-list", "procedure: [iso9283_repeatability]\n", "procedure: expected one of"),
    ("huge-integer", ISO + "parameters: {cycles: " + "9" * 5000 + "}\n", "integer with too many digits"),
    ("huge-float", ISO + "parameters: {cube_edge_m: " + "9" * 400 + "}\n", "parameters.cube_edge_m:"),
    ("deep", "procedure: " + "[" * 5000 + "]" * 5000 + "\n", "nested too deeply"),
    ("deep-mapping", ISO + "parameters: " + "{a: " * 100 + "1" + "}" * 100 + "\n", "nested more than 32"),
    ("recursive-alias", "procedure: &a [*a]\n", "recursive alias"),
    ("billion-laughs", _bomb(), "alias bomb"),
    ("nan", ISO + "parameters: {cube_center_m: [.nan, 0, 0]}\n", "input should be a finite number (got nan)"),
    ("inf", ISO + "parameters: {settle_time_s: .inf}\n", "input should be a finite number (got inf)"),
    ("tiny-step", "procedure: displacement_calibration\nparameters: {step_mm: 1e-9}\n",
     "parameters.step_mm: step_mm gives more than 100000 points per line"),
    ("one-repeat", "procedure: angle_calibration\nparameters: {repeats: 1}\n",
     "parameters.repeats: repeats is 1; the calibration fit needs at least 2 repeats"),
    ("record-path-up", "procedure: displacement_calibration\nparameters: {record_path: ../../x.json}\n",
     "parameters.record_path: expected a path relative to the runs folder, without '..'"),
    ("record-path-absolute", "procedure: angle_calibration\nparameters: {record_path: /etc/x.json}\n",
     "parameters.record_path: expected a path relative to the runs folder"),
]


@pytest.mark.parametrize("text, expected", [case[1:] for case in HOSTILE_PROCEDURES],
                         ids=[case[0] for case in HOSTILE_PROCEDURES])
def test_a_hostile_procedure_is_one_line(tmp_path, capsys, station, text, expected):
    path = _write(tmp_path / "p.yaml", text)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.process_time()  # CPU, not wall: a loaded host stretches the wall time, an expansion burns CPU
    line = _one_line(capsys, main(["validate", str(path)]))
    assert expected in line and line.startswith(str(path))
    # The same file given to run: refused before any run is stored.
    line = _one_line(capsys, main(["run", str(path), "--station", str(station), "--runs-dir", str(tmp_path / "r")]))
    assert expected in line
    assert time.process_time() - start < 10
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200_000  # KiB: no expansion


def test_a_file_too_large_is_not_read(tmp_path, capsys):
    path = tmp_path / "big.yaml"
    with open(path, "w", encoding="utf-8") as handle:
        handle.write(ISO + "parameters: {axes: [")
        handle.write("x, " * 2_000_000)
        handle.write("x]}\n")
    line = _one_line(capsys, main(["validate", str(path)]))
    assert "bytes; a YAML file may have at most 4194304 bytes" in line


@pytest.mark.parametrize("kind", ["fifo", "device", "folder", "missing"])
def test_fifos_devices_and_folders_are_refused_not_read(tmp_path, capsys, station, kind):
    if kind == "fifo":
        path = tmp_path / "fifo.yaml"
        os.mkfifo(path)  # no writer: reading it would block forever
    else:
        path = {"device": Path("/dev/zero"), "folder": tmp_path, "missing": tmp_path / "none.yaml"}[kind]
    expected = {"fifo": "not a regular file", "device": "not a regular file", "folder": "is a folder",
                "missing": "No such file or directory"}[kind]
    assert expected in _one_line(capsys, main(["validate", str(path)]))
    line = _one_line(capsys, main(["run", str(path), "--station", str(station), "--runs-dir", str(tmp_path / "r")]))
    assert expected in line or (kind == "missing" and "no such procedure file" in line), line
    iso = _write(tmp_path / "iso.yaml", ISO)
    assert expected in _one_line(capsys, main(["run", str(iso), "--station", str(path), "--runs-dir",
                                               str(tmp_path / "r")]))


def _station_with(station: Path, tmp_path: Path, **changes) -> Path:
    data = yaml.safe_load(station.read_text(encoding="utf-8"))
    for dotted, value in changes.items():
        *parents, last = dotted.split("__")
        target = data
        for key in parents:
            target = target[key]
        target[last] = value
    path = tmp_path / "station-changed.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def test_calibration_records_that_are_folders_or_missing_are_one_line_each(tmp_path, capsys, station):
    not_json = _write(tmp_path / "record.json", "{not json")
    path = _station_with(station, tmp_path, calibration__record=[str(tmp_path), str(tmp_path / "none.json"),
                                                                 str(not_json)])
    assert main(["validate", str(path)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and "Traceback" not in "".join(err)
    assert "is a folder, not a calibration record" in err[0]
    assert "No such file or directory" in err[1]
    assert "is not a calibration record" in err[2]
    iso = _write(tmp_path / "iso.yaml", ISO)
    line = _one_line(capsys, main(["run", str(iso), "--station", str(path), "--runs-dir", str(tmp_path / "r")]))
    assert line.startswith("calibration.record: ") and "is a folder" in line


def test_nan_in_a_station_is_refused_with_its_line(tmp_path, capsys, station):
    path = _station_with(station, tmp_path, envelope__max_speed=float("nan"))
    line = _one_line(capsys, main(["validate", str(path)]))
    assert ": envelope.max_speed: input should be a finite number (got nan)" in line
    path = _station_with(station, tmp_path, geometry__screens__x__origin=[0.0, float("inf"), 0.0])
    line = _one_line(capsys, main(["validate", str(path)]))
    assert "geometry: expected finite numbers; screens.x.origin[1] is NaN or infinite" in line


def test_validate_station_procedure_dry_runs_and_collapses_repeated_problems(tmp_path, capsys, station):
    far = _write(tmp_path / "far.yaml", ISO + "parameters: {cycles: 30, cube_center_m: [0.035, 0.035, 0.3]}\n")
    assert main(["validate", str(station), str(far)]) == 1
    captured = capsys.readouterr()
    assert f"{far}: OK (iso9283_repeatability)" in captured.out  # the file itself is valid ...
    lines = captured.err.strip().splitlines()  # ... its plan is not: one line per kind of problem
    assert len(lines) == 2, lines
    assert all(line.startswith(f"{far}: dry run on {station}: step transform/c000/P1: ") for line in lines)
    assert "outside the envelope" in lines[0] and lines[0].endswith("(… and 154 more points)")
    assert "cross not on its screen" in lines[1]
    good = Path(__file__).resolve().parents[1] / "procedures" / "displacement_calibration.yaml"
    assert main(["validate", str(station), str(good)]) == 0
    assert f"dry run on {station}: OK (405 steps)" in capsys.readouterr().out


@pytest.fixture
def runs_with_many_runs(tmp_path) -> Path:
    with RunStore(tmp_path) as store:
        for _ in range(300):
            store.create_run(procedure="iso9283_repeatability", parameters={}, station={}, software_version="t",
                             procedure_name="x" * 200)
    return tmp_path


def test_output_to_a_reader_that_goes_away_ends_quietly(runs_with_many_runs):
    pipeline = subprocess.run(f"{sys.executable} -m procedures.cli runs --json --runs-dir {runs_with_many_runs} "
                              "| head -1", shell=True, cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert json.loads(pipeline.stdout)["procedure"] == "iso9283_repeatability"
    assert pipeline.stderr == ""


def test_output_into_a_missing_folder_is_one_line(runs_with_many_runs, tmp_path, capsys):
    run_id = RunStore(runs_with_many_runs).list_runs()[0]["id"]
    for command in (["export", run_id, "--json"], ["export", run_id, "--csv"], ["report", run_id]):
        line = _one_line(capsys, main([*command, "-o", str(tmp_path / "no" / "such" / "out"), "--runs-dir",
                                       str(runs_with_many_runs)]))
        assert line == f"cannot write {tmp_path / 'no' / 'such' / 'out'}: No such file or directory"


@pytest.mark.parametrize("argv", [["--seed", "1" + "0" * 30], ["--seed", "-1"], ["--pause-timeout", "nan"]])
def test_absurd_numbers_on_the_command_line_are_refused_by_the_parser(tmp_path, capsys, argv):
    with pytest.raises(SystemExit) as exited:
        main(["run", "iso9283_repeatability", "--station", "sim", "--runs-dir", str(tmp_path), *argv])
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "error: argument" in err
    assert not (tmp_path / "sim").exists()  # refused before any cell was started


def test_an_unforeseen_error_is_one_line_and_its_traceback_goes_to_the_log(runs_with_many_runs, capsys, monkeypatch):
    def broken(store, run_id):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(RunStore, "samples", broken)  # a bug in what ``show`` calls
    run_id = RunStore(runs_with_many_runs).list_runs()[0]["id"]
    line = _one_line_internal(capsys, main(["show", run_id, "--runs-dir", str(runs_with_many_runs)]))
    log = runs_with_many_runs / ERROR_LOG
    assert line == f"instrument: internal error: ZeroDivisionError: a bug (traceback in {log})"
    assert "Traceback (most recent call last)" in log.read_text() and "a bug" in log.read_text()


def _one_line_internal(capsys, code: int) -> str:
    captured = capsys.readouterr()
    assert code == 1 and "Traceback" not in captured.err
    (line,) = captured.err.strip().splitlines()
    return line
