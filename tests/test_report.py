"""Reports and exports of finished runs (fake cell with a ground-truth log)."""

import csv
import io
import json

import pytest

from procedures._api import open_engine
from procedures._report import export_csv, export_json, render_report
from tests.fakes import FakeCell, FakeScience, write_station


def _run(tmp_path, kind, **params):
    truth = tmp_path / "truth.jsonl"
    station = write_station(tmp_path / "station.yaml", truth_log=str(truth))
    cell = FakeCell(seed=7, truth_log=truth)
    body = ", ".join(f"{k}: {v}" for k, v in {"settle_time_s": 0, "frames_per_pose": 1, **params}.items())
    proc = tmp_path / f"{kind}.yaml"
    proc.write_text(f"procedure: {kind}\nparameters: {{{body}}}\n")
    with open_engine(tmp_path / "runs", procedure=proc, station=station, science=FakeScience(cell),
                     devices=cell.devices(), operator=cell.operator) as engine:
        assert engine.execute() == "FINISHED"
        run = engine.store.get_run(engine.run_id)
        return run, engine.store.samples(engine.run_id), engine.store.events(engine.run_id)


def test_iso_report_has_the_table_truth_and_plots(tmp_path):
    run, samples, events = _run(tmp_path, "iso9283_repeatability", cycles=5)
    html = render_report(run, samples, events)
    for header in ("RP<sub>l</sub> (µm)", "RP<sub>a</sub> (°)", "RP<sub>b</sub> (°)", "RP<sub>c</sub> (°)",
                   "AP<sub>P</sub> (µm)"):
        assert header in html
    for label in ("P1", "P2", "P3", "P4", "P5"):
        assert f"<td class=l>{label}</td>" in html and f"{label} (true)" in html
    assert html.count("<svg") == 10  # two scatter plots per point
    # the table shows RP_l in µm: the stored value (m) × 1e6, with 2 decimals
    rp_l = run["results"]["points"]["P1"]["stats"]["rp_l"]
    assert f"<td>{rp_l * 1e6:.2f} <small>[" in html
    assert "<script" not in html and "http://" not in html.replace("http://www.w3.org/2000/svg", "")
    assert run["id"] in html and "fake cell" in html


def test_calibration_report_has_curves_before_and_after(tmp_path):
    run, samples, events = _run(tmp_path, "angle_calibration", repeats=2, axes="[z]")
    html = render_report(run, samples, events)
    assert "c: error against measured value" in html and "error (″)" in html
    assert "Reference against simulated truth" in html
    assert run["results"]["record_id"] in html


def test_exports(tmp_path):
    run, samples, events = _run(tmp_path, "iso9283_repeatability", cycles=2)
    rows = list(csv.DictReader(io.StringIO(export_csv(samples))))
    assert len(rows) == len(samples) == 15
    assert float(rows[3]["solved_x_m"]) == pytest.approx(samples[3].solved["pose"][0])
    assert rows[0]["step_key"] == "transform/c000/P1"
    data = json.loads(export_json(run, samples, events))
    assert data["run"]["id"] == run["id"] and len(data["samples"]) == 15
    assert data["samples"][0]["commanded"]["tcp_pose"] == samples[0].commanded["tcp_pose"]
