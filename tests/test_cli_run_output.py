"""What ``instrument run``/``resume`` show: progress (terminal or heartbeat), the end of a run, ``--set``.

The runs are the fake cell's (``tests/fakes.py``), driven through the CLI's own ``drive`` with the
display the CLI builds, so what is printed is what an operator sees.
"""

from __future__ import annotations

import argparse
import io
import json
import re
from pathlib import Path

import pytest

from procedures.cli import Display, drive, main
from procedures.engine import open_engine
from procedures.station import ConfigError
from procedures.store import RunState
from tests.fakes import FakeCell, FakeScience, write_station

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def _procedure(tmp_path: Path, kind: str, **params) -> Path:
    body = ", ".join(f"{k}: {v}" for k, v in {"settle_time_s": 0, "frames_per_pose": 1, **params}.items())
    path = tmp_path / f"{kind}.yaml"
    path.write_text(f"procedure: {kind}\nparameters: {{{body}}}\n")
    return path


def _drive(tmp_path: Path, procedure: Path, display: Display | None, *, quiet=False, jsonl=False, move_delay=0.0,
           overrides=()):
    station = write_station(tmp_path / "station.yaml")
    cell = FakeCell(seed=6, move_delay=move_delay)
    args = argparse.Namespace(quiet=quiet, jsonl=jsonl)
    with open_engine(tmp_path / "runs", procedure=procedure, station=station, science=FakeScience(cell),
                     devices=cell.devices(), operator=cell.operator, listener=display, overrides=list(overrides)
                     ) as engine:
        code = drive(engine, args, display)
        run = engine.store.get_run(engine.run_id)
    return code, run


def test_an_iso_run_ends_with_its_rp_table_and_report(tmp_path, capsys):
    code, run = _drive(tmp_path, _procedure(tmp_path, "iso9283_repeatability", cycles=3), Display("quiet"))
    out = capsys.readouterr().out.splitlines()
    assert code == 0 and out[0].startswith(f"run {run['id']}: FINISHED after ")
    header = out[1].split()
    assert header[:3] == ["point", "n", "RP_l"]
    stats = run["results"]["points"]["P4"]["stats"]
    (p4,) = [line for line in out if line.startswith("P4 ")]
    lo, hi = stats["rp_l_ci"]
    assert f"{stats['rp_l'] * 1e6:.2f} ± {(hi - lo) / 2 * 1e6:.2f}" in p4  # the interval's half-width, no U here
    assert f"{stats['ap_p'] * 1e6:.2f}" in p4
    assert any("half-width of the 95 % confidence interval" in line for line in out)
    assert run["results"]["compensation"] == []  # no calibration record in force: the table says so
    assert ("uncompensated: no calibration record was in force, so these figures carry the instrument's own "
            "systematic errors (run the calibrations, then measure with their records in force)") in out
    report = Path(out[-1].removeprefix("report: "))
    assert report == tmp_path / "runs" / run["id"] / "report.html" and run["id"] in report.read_text()


def test_a_calibration_ends_with_its_record(tmp_path, capsys):
    code, run = _drive(tmp_path, _procedure(tmp_path, "displacement_calibration", axes="[y]", repeats=2),
                       Display("quiet"))
    out = capsys.readouterr().out.splitlines()
    assert code == 0 and out[1] == f"record {run['results']['record_path']} ({run['results']['record_id']})"


def test_held_out_residuals_of_a_real_calibration_fit_are_shown():
    """The instrument's own calibration fit on data with a known error curve: the lines show the
    held-out RMS of the method the record kept (the lowest), in µm, beside its noise floor."""
    import numpy as np

    from procedures.report import calibration_lines, held_out_rows
    from procedures.station import InstrumentScience

    rng = np.random.default_rng(3)
    rows = []
    for group in range(3):
        for repeat in range(2):
            for point in range(8):
                reference = 0.005 * point
                measured = reference + 20e-6 * np.sin(60 * reference) + 0.5e-6 * rng.standard_normal()
                rows.append({"group": group, "repeat": repeat, "point": point, "nominal": reference,
                             "measured": float(measured), "reference": reference, "datum_set_at": None})
    fit = InstrumentScience().fit_calibration("displacement", {"y": rows}, {"run_id": "t", "date": "",
                                                                            "references": []})
    results = {"record_path": "/r.json", "record_id": "abc", "summary": fit.summary}
    (row,) = held_out_rows(results)
    lopo = [r for r in fit.summary["evaluation"]["rows"] if r["scheme"] == "leave-one-point-out"]
    best = min(lopo, key=lambda r: r["rms"])
    assert (row["method"], row["rms"]) == (best["method"], best["rms"])
    assert 0.2e-6 < row["rms"] < 5e-6  # near the 0.5 µm noise, far below the 20 µm error it corrected
    lines = calibration_lines(results)
    assert lines[1] == "held-out (leave-one-point-out) residuals after compensation:"
    assert re.match(rf"^y\s+{re.escape(best['method'])}\s+{best['rms'] * 1e6:.3f} µm", lines[3])


def test_quiet_prints_exactly_one_line(tmp_path, capsys):
    code, run = _drive(tmp_path, _procedure(tmp_path, "iso9283_repeatability", cycles=2), Display("quiet"),
                       quiet=True)
    captured = capsys.readouterr()
    assert code == 0 and captured.err == ""
    assert captured.out.splitlines() == [f"{run['id']} FINISHED"]
    assert (tmp_path / "runs" / run["id"] / "report.html").is_file()  # written all the same


def test_the_jsonl_done_event_carries_results_and_report(tmp_path, capsys):
    code, run = _drive(tmp_path, _procedure(tmp_path, "iso9283_repeatability", cycles=2), Display("jsonl"),
                       jsonl=True)
    events = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    progress = [e for e in events if e["event"] == "progress"]
    assert [e["cycle"] for e in progress if e["phase"] == "iso"] == [0] * 5 + [1] * 5
    assert all(e["cycles"] == 2 and e["phases"] == 2 for e in progress if e["phase"] == "iso")
    done = events[-1]
    assert done["event"] == "done" and done["state"] == "FINISHED" and code == 0
    assert done["report"].endswith("report.html") and Path(done["report"]).is_file()
    p1 = [p for p in done["results"]["points"] if p["point"] == "P1"][0]
    assert p1["rp_l"]["value"] == run["results"]["points"]["P1"]["stats"]["rp_l"]


def test_heartbeat_lines_when_stderr_is_not_a_terminal(tmp_path, capsys):
    stream = io.StringIO()  # not a terminal
    display = Display("bar", stream=stream, heartbeat_s=0.2)
    code, run = _drive(tmp_path, _procedure(tmp_path, "iso9283_repeatability", cycles=3), display,
                       move_delay=0.08)
    assert code == 0
    lines = stream.getvalue().splitlines()
    beats = [line for line in lines if " ETA " in line]
    assert len(beats) >= 2, lines
    assert any(re.search(r"cycle [1-3]/3 P[1-5] · iso 2/2 · iso9283_repeatability · \d+/20 \(", b) for b in beats)
    assert all("\r" not in line and "\x1b" not in line for line in lines)  # plain lines for a file or a pipe
    assert any(line.endswith("FINISHED") for line in lines)


def test_after_the_last_pose_the_heartbeat_says_analysing_with_its_own_eta(tmp_path):
    """Once every pose is measured the heartbeat says what runs (the analysis, k of N passes, its own ETA), not
    'waiting N s since the last pose' with the poses' ETA."""
    stream = io.StringIO()
    display = Display("bar", stream=stream, heartbeat_s=0.2)
    _drive(tmp_path, _procedure(tmp_path, "iso9283_repeatability", cycles=3), display)
    assert display.analysis == {**display.analysis, "event": "analysis", "stage": "results", "done": 0}
    display.last_progress = {**display.last_progress, "time": 0.0}  # the last pose long ago
    assert "analysing the results · 20/20 poses measured · ETA" in display.status_line()
    display(dict(event="analysis", stage="uncertainty", done=3, total=9, eta_s=125.0))
    line = display.status_line()
    assert line.endswith("analysing (uncertainty, 3 of 9) · 20/20 poses measured · ETA 0:02:05")
    assert "waiting" not in line


def test_the_terminal_display_fits_its_width(tmp_path, monkeypatch):
    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    monkeypatch.setenv("COLUMNS", "64")
    stream = Terminal()
    display = Display("bar", stream=stream)
    code, _ = _drive(tmp_path, _procedure(tmp_path, "iso9283_repeatability", cycles=2), display)
    assert code == 0
    screen = [ANSI.sub("", line) for line in re.split(r"[\r\n]", stream.getvalue())]
    assert any("cycle 2/2" in line for line in screen) and any("ETA" in line for line in screen)
    assert max(len(line) for line in screen) <= 64


def test_set_overrides_are_validated_stored_and_shown(tmp_path):
    procedure = _procedure(tmp_path, "iso9283_repeatability", cycles=5)
    code, run = _drive(tmp_path, procedure, Display("quiet"), quiet=True, overrides=["cycles=2", "save_frames=never"])
    assert code == 0 and run["parameters"]["cycles"] == 2 and run["parameters"]["save_frames"] == "never"
    assert run["total_steps"] == 5 + 2 * 5
    assert run["procedure_text"].startswith("# iso9283_repeatability.yaml run with --set cycles=2 "
                                            "--set save_frames=never\n")
    report = (tmp_path / "runs" / run["id"] / "report.html").read_text(encoding="utf-8")
    assert "<h1>ISO 9283 pose repeatability and accuracy — 2 cycles</h1>" in report  # the kind's title, as run
    for bad, expected in (
        ["cycles=thirty"], "--set cycles=thirty: parameters.cycles: input should be a valid integer",
    ), (["cycle=3"], "--set cycle=3: parameters.cycle: unknown field"), (["cycles"], "--set cycles: expected "
                                                                          "PARAMETER=VALUE"):
        with pytest.raises(ConfigError) as refused:
            _drive(tmp_path, procedure, Display("quiet"), overrides=bad)
        assert len(refused.value.problems) == 1 and refused.value.problems[0].startswith(expected)


def test_set_and_calibration_mistakes_are_one_line_before_anything_starts(tmp_path, capsys):
    station = write_station(tmp_path / "station.yaml")
    assert main(["run", "iso9283_repeatability", "--station", str(station), "--set", "cycles=1",
                 "--runs-dir", str(tmp_path / "runs")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["--set cycles=1: parameters.cycles: input should be greater than or equal to 2 (got 1)"]
    assert main(["run", "iso9283_repeatability", "--station", str(station), "--calibration", "x.json",
                 "--runs-dir", str(tmp_path / "runs")]) == 1
    assert capsys.readouterr().err.strip().startswith("--calibration x.json: no such file")
    record = tmp_path / "record.json"
    record.write_text("{}")
    assert main(["run", "iso9283_repeatability", "--station", str(station), "--calibration", str(record),
                 "--runs-dir", str(tmp_path / "runs")]) == 1
    assert capsys.readouterr().err.strip() == ("--calibration goes with --station sim; a station file names its "
                                               "records in calibration.record")


def test_a_run_records_the_robot_it_measured(tmp_path, capsys):
    _, run = _drive(tmp_path, _procedure(tmp_path, "iso9283_repeatability", cycles=2), Display("quiet"))
    assert run["robot_serial"] == "20235500123" and run["robot_model"] == "UR5"
    assert RunState(run["state"]) == RunState.FINISHED


def test_every_kind_records_the_cells_robot(tmp_path):
    """The angle calibration does not move the robot, but its run belongs to that robot's cell: it records the
    robot too, so the faces list the robot once (not once by serial and once by station name)."""
    _, run = _drive(tmp_path, _procedure(tmp_path, "angle_calibration", axes="[z]", repeats=2, step_deg=0.5),
                    Display("quiet"))
    assert RunState(run["state"]) == RunState.FINISHED, run["reason"]
    assert run["robot_serial"] == "20235500123" and run["robot_model"] == "UR5"


def test_the_demos_eta_adds_the_runs_still_to_come():
    from procedures.demo import DemoProgress

    progress = DemoProgress([(100, 3), (50, 3), (20, 1)])
    progress.display = Display("quiet")
    progress.display.last_progress = {"pace_s": 0.3, "setup_s": 2.0}
    assert progress.later_s() == pytest.approx(50 * 0.3 + 3 * 2.0 + 20 * 0.3 + 1 * 2.0)
    progress.current, progress.overheads = 1, [4.0]
    assert progress.later_s() == pytest.approx(20 * 0.3 + 1 * 2.0 + 4.0)
    progress.current = 2
    assert progress.later_s() == 0.0


@pytest.mark.parametrize(("warm_up_s", "listed"), [(0, True), (600, False)])
def test_no_warm_up_is_a_deviation(tmp_path, warm_up_s, listed):
    """ISO 9283 tests a warm robot: a run with no warm-up (0 s declared, none run) lists it as a deviation."""
    _, run = _drive(tmp_path, _procedure(tmp_path, "iso9283_repeatability", cycles=2, warm_up_s=warm_up_s),
                    Display("quiet"))
    codes = [d["code"] for d in run["results"]["deviations"]]
    assert ("no_warm_up" in codes) is listed
