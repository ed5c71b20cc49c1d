"""Reports and exports of finished runs (fake cell with a ground-truth log).

The HTML is read back with a small parser and every number is checked against the stored results
it was made from (SI in the store, µm and arc-seconds in the report).
"""

from __future__ import annotations

import copy
import csv
import io
import json
import math
import re
from html import unescape
from html.parser import HTMLParser
from pathlib import Path

import pytest

from instrument import ARCSEC
from procedures.engine import open_engine
from procedures.report import export_csv, export_json, quantity, render_report
from tests.fakes import FakeCell, FakeScience, write_station


def fake_run(tmp_path: Path, kind: str, name: str | None = None, **params):
    """A finished run of ``kind`` on the fake cell: (run row, samples, events)."""
    truth = tmp_path / "truth.jsonl"
    station = write_station(tmp_path / "station.yaml", truth_log=str(truth))
    cell = FakeCell(seed=7, truth_log=truth)
    body = ", ".join(f"{k}: {v}" for k, v in {"settle_time_s": 0, "frames_per_pose": 1, **params}.items())
    proc = tmp_path / f"{kind}.yaml"
    proc.write_text(f"procedure: {kind}\n" + (f"name: {name}\n" if name else "") + f"parameters: {{{body}}}\n")
    with open_engine(tmp_path / "runs", procedure=proc, station=station, science=FakeScience(cell),
                     devices=cell.devices(), operator=cell.operator) as engine:
        assert engine.execute() == "FINISHED"
        run = engine.store.get_run(engine.run_id)
        return run, engine.store.samples(engine.run_id), engine.store.events(engine.run_id)


NEW_RESULT_KEYS = ("results_version", "figures", "uncertainty", "test_conditions", "deviations", "evaluation",
                   "before_after", "residual_uncertainty", "reference_vs_truth", "approach")


def as_stored_by_older_code(run: dict) -> dict:
    """The run as code before docs/results.md stored it: no figure objects, conditions, deviations,
    honest calibration data (what the report must still render from the ISO statistics and curves)."""
    run = copy.deepcopy(run)
    results = run["results"]
    for key in NEW_RESULT_KEYS:
        results.pop(key, None)
    for point in (results.get("points") or {}).values():
        for key in ("cycles", "t_measured", "approach", "commanded_in_base"):
            point.pop(key, None)
    for curve in (results.get("curves") or {}).values():
        for key in ("error_before_datum_removed", "error_after_datum_removed", "error_after_held_out", "direction"):
            curve.pop(key, None)
    return run


class Tables(HTMLParser):
    """Every table of a document: caption and rows of cell texts (tags stripped, <br> as newline)."""

    def __init__(self, html: str) -> None:
        super().__init__()
        self.tables: list[dict] = []
        self._stack: list[dict] = []
        self._cell: list[str] | None = None
        self._caption: list[str] | None = None
        self.feed(html)

    def handle_starttag(self, tag, attrs):
        if tag == "table":
            self._stack.append({"caption": "", "rows": [], "attrs": dict(attrs)})
        elif tag == "tr" and self._stack:
            self._stack[-1]["rows"].append([])
        elif tag in ("td", "th") and self._stack:
            self._cell = []
        elif tag == "br" and self._cell is not None:
            self._cell.append("\n")
        elif tag == "caption":
            self._caption = []

    def handle_endtag(self, tag):
        if tag == "table" and self._stack:
            self.tables.append(self._stack.pop())
        elif tag in ("td", "th") and self._cell is not None and self._stack:
            self._stack[-1]["rows"][-1].append("".join(self._cell).strip())
            self._cell = None
        elif tag == "caption" and self._caption is not None:
            self._stack[-1]["caption"] = "".join(self._caption)
            self._caption = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)
        elif self._caption is not None:
            self._caption.append(data)

    def find(self, caption_start: str) -> list[list[str]]:
        return next(t["rows"] for t in self.tables if t["caption"].startswith(caption_start))


def rows_by_label(rows: list[list[str]]) -> dict[str, list[str]]:
    return {row[0]: row for row in rows if row}


@pytest.fixture(scope="module")
def iso5(tmp_path_factory):
    """A 5-cycle ISO run whose procedure file calls itself "30 cycles"."""
    return fake_run(tmp_path_factory.mktemp("iso5"), "iso9283_repeatability", name="'ISO 9283, 30 cycles'", cycles=5)


def test_rp_table_shows_the_stored_figures_in_micrometres_and_arcseconds(iso5):
    run, samples, events = iso5
    results = run["results"]
    rows = rows_by_label(Tables(render_report(run, samples, events)).find("Pose repeatability RP"))
    assert rows["point"][2:] == ["RPl (µm)", "RPa (″)", "RPb (″)", "RPc (″)"]
    for label in ("P1", "P2", "P3", "P4", "P5"):
        stats, true = results["points"][label]["stats"], results["points"][label]["true_stats"]
        cells = rows[label]
        assert cells[1] == "5"
        lo, hi = stats["rp_l_ci"]
        assert cells[2] == f"{stats['rp_l'] * 1e6:.2f}\n[{lo * 1e6:.2f}, {hi * 1e6:.2f}]"
        for cell, key in zip(cells[3:], ("rp_a", "rp_b", "rp_c")):
            assert cell == f"{stats[key] / ARCSEC:.2f}\n{math.degrees(stats[key]):.6f}°"  # ″, degrees beside
        assert rows[f"{label} (true)"][2].startswith(f"{true['rp_l'] * 1e6:.2f}")
    worst = max(results["order"], key=lambda p: results["points"][p]["stats"]["rp_l"])
    assert rows["worst case"][2] == f"{results['points'][worst]['stats']['rp_l'] * 1e6:.2f}\nat {worst}"


def test_true_rows_only_where_like_for_like_and_said_so(iso5):
    """RP's true rows compare like for like; the cell's true AP does not (its true tool point carries mounting
    errors the instrument cannot see), so the AP table has none and the note says why, for old and new runs."""
    run, samples, events = iso5
    for shown in (run, with_stored_figures(as_stored_by_older_code(run))):
        html = render_report(shown, samples, events)
        tables = Tables(html)
        assert any(label.endswith("(true)") for label in rows_by_label(tables.find("Pose repeatability RP")))
        assert not any(label.endswith("(true)") for label in rows_by_label(tables.find("Pose accuracy AP")))
        text = " ".join(html.split())
        assert "Pose accuracy has no true row" in text and "like with like" not in text
        assert "like for like and measured − true is the instrument's error" in text


def test_ap_table_has_components_and_a_worst_case_by_magnitude(iso5):
    run, samples, events = iso5
    results = run["results"]
    rows = rows_by_label(Tables(render_report(run, samples, events)).find("Pose accuracy AP"))
    assert rows["point"][2:] == ["APP (µm)", "APx (µm)", "APy (µm)", "APz (µm)", "APa (″)", "APb (″)", "APc (″)"]
    for label in results["order"]:
        stats = results["points"][label]["stats"]
        assert rows[label][2] == f"{stats['ap_p'] * 1e6:.2f}"
        assert rows[label][3] == "—"  # the fake core gives no AP_x: a dash, not a made-up number
        assert rows[label][6].startswith(f"{stats['ap_a'] / ARCSEC:.2f}\n")
    worst = max(results["order"], key=lambda p: abs(results["points"][p]["stats"]["ap_a"]))
    value = results["points"][worst]["stats"]["ap_a"]
    assert rows["worst case"][6].startswith(f"{value / ARCSEC:.2f}\n") and rows["worst case"][6].endswith(f"at {worst}")


def test_title_and_banner_say_5_cycles_when_the_name_says_30(iso5):
    run, samples, events = iso5
    html = render_report(as_stored_by_older_code(run), samples, events)  # the deviations read off the run
    title = re.search(r"<h1>(.*?)</h1>", html).group(1)
    assert "5 cycles" in title and "30" not in title
    banner = re.search(r"<div class=banner id=deviations>(.*?)</div>", html).group(1)
    assert "5 cycles measured (ISO 9283 asks for 30)" in banner
    assert "no calibration record was in force" in banner  # apply_compensation true, no record
    assert "the name says 30 cycles; this run has 5" in html
    assert html.index("id=deviations") < html.index("id=results")  # at the top


def test_a_30_cycle_run_without_compensation_has_no_cycle_deviation(tmp_path):
    run, samples, events = fake_run(tmp_path, "iso9283_repeatability", cycles=30, apply_compensation="false")
    html = render_report(as_stored_by_older_code(run), samples, events)
    banner = re.search(r"<div class=banner id=deviations>(.*?)</div>", html).group(1)
    assert "no compensation" in banner and "cycles measured" not in banner
    assert "— 30 cycles</h1>" in html


def test_sign_off_block_test_conditions_and_appendix(iso5):
    run, samples, events = iso5
    html = render_report(as_stored_by_older_code(run), samples, events)  # conditions from parameters and station
    tables = Tables(html)
    signoff = next(t["rows"] for t in tables.tables if t["attrs"].get("class") == "signoff")
    assert [r[0] for r in signoff] == ["", "Prepared by", "Checked by", "Approved by"]
    assert signoff[0][1:] == ["name", "function", "date", "signature"]
    conditions = rows_by_label(next(t["rows"] for t in tables.tables
                                    if any(r and r[0] == "TCP speed" for r in t["rows"])))
    # 50 % of the fake station's 0.5 m/s limit; P1's commanded tool point in M, in mm
    assert conditions["TCP speed"][1].startswith("250.0 mm/s (50 % of")
    p1 = run["results"]["points"]["P1"]["commanded"]
    assert conditions["P1 commanded"][1].startswith("(" + ", ".join(f"{v * 1e3:.3f}" for v in p1[:3]) + ") mm")
    assert html.index("id=signoff") < html.index("id=appendix")
    appendix = html[html.index("id=appendix"):]
    assert "Station snapshot" in appendix and "Procedure file" in appendix and "Parameters" in appendix
    assert "<script" not in html and "http://" not in html.replace("http://www.w3.org/2000/svg", "")


def test_appendix_json_is_rounded_for_display(iso5):
    run, samples, events = iso5
    run = copy.deepcopy(run)
    run["station"]["envelope"]["max_tilt"] = 0.1 + 0.2  # 0.30000000000000004
    html = unescape(render_report(run, samples, events))
    assert "0.30000000000000004" not in html and '"max_tilt": 0.3' in html
    # pose arrays are counted, not listed (they are in the JSON export)
    assert '"poses": "5 entries (instrument export RUN --json)"' in html


def test_a_failed_runs_long_reason_is_one_line_with_the_full_text_in_the_appendix(iso5):
    run, samples, events = iso5
    run = copy.deepcopy(run)
    lines = [f"Traceback line {i}: something deep went wrong" for i in range(50)]
    reason = "robot: moveL failed: timeout\n" + "\n".join(lines)
    run.update(state="FAILED", exit_status="fail", results=None, reason=reason)
    html = render_report(run, samples, events)
    header = rows_by_label(Tables(html).tables[0]["rows"])
    assert header["reason"][0] == "reason"
    assert header["reason"][1].startswith("robot: moveL failed: timeout …") and "Traceback" not in header["reason"][1]
    appendix = html[html.index("id=appendix"):]
    assert "Traceback line 49" in appendix and "Reason (full text)" in appendix
    assert "No results: the run has not finished." in html


# A run as the data side stores it (docs/results.md): figure objects with U, deviations, conditions.
def with_stored_figures(run: dict) -> dict:
    run = copy.deepcopy(run)
    results = run["results"]
    figures = {}
    for label in results["order"]:
        stats, true = results["points"][label]["stats"], results["points"][label]["true_stats"]
        figures[label] = {
            key: {"value": stats[key] * 0.99, "expanded_uncertainty": abs(stats[key]) * (0.4 if key == "ap_c" else .05),
                  "coverage_factor": 2, "confidence_interval": stats.get(f"{key}_ci"), "true": true[key],
                  "unit": "m" if key in ("rp_l", "ap_p") else "rad",
                  "budget": {"meets_25_percent_rule": key != "ap_c", "ratio_to_characteristic": 0.4}}
            for key in ("rp_l", "rp_a", "rp_b", "rp_c", "ap_p", "ap_a", "ap_b", "ap_c")}
        figures[label]["dap_p"] = {"value": 1.5e-6, "expanded_uncertainty": 0.5e-6, "coverage_factor": 2,
                                   "confidence_interval": None, "true": 1.4e-6, "unit": "m", "budget": None}
    results["figures"] = {"points": figures, "distances": {"P2-P4": {
        "ad_p": {"value": 3.2e-6, "expanded_uncertainty": 1.1e-6, "coverage_factor": 2, "confidence_interval": None,
                 "true": 3.0e-6, "unit": "m", "budget": None}}}, "directions": {}}
    results["uncertainty"] = {"evaluated": True, "method": "GUM budget, Monte Carlo", "draws": 1000, "seed": 0,
                              "coverage_factor": 2, "budget": {"terms": [
                                  {"name": "frame noise", "source": "calibration noise floor", "correlation": "pose",
                                   "distribution": "normal", "dof": 90.0,
                                   "standard_uncertainty": {"x": 1.2e-6, "y": 1.1e-6, "z": 1.0e-6,
                                                            "a": 5.3e-6, "b": 4.9e-6, "c": 5.0e-6}}]},
                              "noise_estimator": {"used": "calibration noise floor", "why": "one frame per pose"},
                              "outside_validity": {"P3": ["z"]}, "notes": []}
    results["deviations"] = [
        {"code": "cycles_below_30", "severity": "deviation",
         "message": "5 cycles measured at P1 (ISO 9283 asks for 30)"},
        {"code": "uncertainty_above_25_percent", "severity": "deviation", "message": "AP_c: U above 25 % at 5 points"},
        {"code": "environment_not_recorded", "severity": "warning", "message": "no environmental unit"}]
    results["test_conditions"] = {
        "standard": "ISO 9283:1998", "date": "2026-01-02T10:00:00+01:00",
        "operator": {"name": "A. Tester", "source": "INSTRUMENT_OPERATOR"},
        "robot": {"manufacturer": "Universal Robots", "model": "UR5e", "serial_number": "20235500123",
                  "controller_version": "5.15.0", "source": "controller"},
        "payload": {"mass_kg": 1.2, "cog_m": [0.0, 0.0, 0.05], "set_on_robot": True, "rated_mass_kg": 5.0,
                    "percent_of_rated": 24.0},
        "motion": {"speed_m_s": 0.25, "acceleration_m_s2": 1.0, "speed_percent_of_envelope": 50.0,
                   "acceleration_percent_of_envelope": 50.0, "rated_speed_m_s": 1.0, "percent_of_rated_speed": 25.0,
                   "rated_acceleration_m_s2": None, "percent_of_rated_acceleration": None},
        "cube": {"centre_in_m": [0.035, 0.035, 0.035], "edge_m": 0.07, "centre_in_base": [0.485, -0.065, 0.235],
                 "largest_edge_m": 0.3, "points": {"P1": {"in_m": [0.035, 0.035, 0.035],
                                                          "in_base": [0.485, -0.065, 0.235, 3.14159, 0.0, 0.0]}}},
        "cycles": {"planned": 5, "measured": {"P1": 5}},
        "environment": {"source": "interferometer environmental unit", "readings": 12,
                        "start": {"air_temperature_k": 293.65, "pressure_pa": 101325.0, "relative_humidity": 0.45},
                        "end": {"air_temperature_k": 293.85, "pressure_pa": 101300.0, "relative_humidity": 0.46},
                        "drift": {"air_temperature_k": 0.2, "pressure_pa": -25.0, "relative_humidity": 0.01}},
        "warm_up": {"mode": "run", "duration_s": 600.0, "ran_s": 601.2, "moves": 240},
        "measurement_system": {"software_version": "0.1.0", "frames_per_pose": 1, "settle_time_s": 0.0,
                               "calibration_records": [{"id": "sha256:" + "ab" * 32, "path": "runs/x/cal.json",
                                                        "components": ["x"], "methods": {"x": "csf"},
                                                        "date": "2026-01-01T09:00:00", "run_id": "x",
                                                        "validity": {"x": [0.0, 0.07]}, "bidirectional": False,
                                                        "applied": True}]},
    }
    return run


def test_stored_figures_show_value_and_u_and_flag_the_25_percent_rule(iso5):
    run, samples, events = iso5
    run = with_stored_figures(as_stored_by_older_code(run))
    html = render_report(run, samples, events)
    tables = Tables(html)
    rp, ap = rows_by_label(tables.find("Pose repeatability RP")), rows_by_label(tables.find("Pose accuracy AP"))
    for label in run["results"]["order"]:
        fig = run["results"]["figures"]["points"][label]
        rp_l = fig["rp_l"]
        assert rp[label][2].startswith(f"{rp_l['value'] * 1e6:.2f} ± {rp_l['expanded_uncertainty'] * 1e6:.2f}")
        assert rp[label][3].startswith(f"{fig['rp_a']['value'] / ARCSEC:.2f} ± "
                                       f"{fig['rp_a']['expanded_uncertainty'] / ARCSEC:.2f}\n")
        assert rp[f"{label} (true)"][2] == f"{fig['rp_l']['true'] * 1e6:.2f}"
        assert ap[label][8].startswith(f"{fig['ap_c']['value'] / ARCSEC:.2f} ± ") and "†" in ap[label][8]
        assert "†" not in ap[label][2]
    drift = rows_by_label(tables.find("Pose drift"))
    assert drift["P1"][1] == "1.50 ± 0.50\ntrue 1.40"
    assert rows_by_label(tables.find("Distance accuracy AD"))["P2-P4"][1] == "3.20 ± 1.10\ntrue 3.00"
    budget = rows_by_label(tables.find("Standard uncertainty (k = 1)"))
    assert budget["frame noise\ncalibration noise floor"][4:] == (
        ["1.200", "1.100", "1.000"] + [f"{u / ARCSEC:.3f}" for u in (5.3e-6, 4.9e-6, 5.0e-6)])  # µm and ″
    assert "Outside a calibration's validity range" in html and "P3: z" in html


def test_stored_deviations_and_conditions_are_shown(iso5):
    run, samples, events = iso5
    run = with_stored_figures(as_stored_by_older_code(run))
    html = render_report(run, samples, events)
    banner = re.search(r"<div class=banner id=deviations>(.*?)</div>", html).group(1)
    assert "5 cycles measured at P1 (ISO 9283 asks for 30)" in banner and "[uncertainty_above_25_percent]" in banner
    assert "read off the run" not in banner and "no environmental unit" not in banner
    assert "no environmental unit" in re.search(r"<div class='banner warn' id=warnings>(.*?)</div>", html).group(1)
    kv = {}
    for table in Tables(html).tables:
        kv.update({r[0]: r[1] for r in table["rows"] if len(r) == 2})
    assert kv["serial number"] == "20235500123" and kv["model"] == "UR5e"
    assert kv["TCP speed"].startswith("250.0 mm/s (50.0 % of the station's limit; 25.0 % of rated 1000.0 mm/s)")
    assert kv["mass"] == "1.200 kg" and kv["centre of gravity (flange frame)"] == "(0.000, 0.000, 50.000) mm"
    assert kv["operator"].startswith("A. Tester")
    env = rows_by_label(next(t["rows"] for t in Tables(html).tables if t["rows"] and t["rows"][0][1:2] == ["start"]))
    assert env["air temperature"][1:] == ["20.50 °C", "20.70 °C", "0.200 K"]  # K → °C; a drift stays in K
    assert env["pressure"][1:] == ["1013.25 hPa", "1013.00 hPa", "-0.25 hPa"]
    assert "sha256:" + "ab" * 32 in html and "x: 0.00 … 70.00 mm" in html
    # the page header names the robot from its recorded identity
    assert 'content:"Universal Robots UR5e s/n 20235500123"' in html


def test_quantities_convert_by_their_keys():
    assert quantity("speed_m_s", 0.25) == "250.0 mm/s"
    assert quantity("air_temperature_k", 293.15) == "20.00 °C"
    assert quantity("air_temperature_k", 0.5, difference=True) == "0.500 K"
    assert quantity("relative_humidity", 0.455) == "45.5 %"
    assert quantity("cog_m", [0.0, 0.01, 0.05]) == "(0.000, 10.000, 50.000) mm"
    assert quantity("set_on_robot", True) == "yes" and quantity("anything", None) == "—"


def test_calibration_report_removes_each_groups_datum(tmp_path):
    run, samples, events = fake_run(tmp_path, "angle_calibration", repeats=2, axes="[z]")
    run = as_stored_by_older_code(run)  # the per-group statistics computed from the stored curves
    html = render_report(run, samples, events)
    assert run["results"]["record_id"] in html and "Reference against simulated truth" in html
    curve = run["results"]["curves"]["c"]
    rows = [r for r in Tables(html).find("Error = measured − reference") if r and r[0] == "c"]
    assert [r[1] for r in rows] == ["0", "1", "2", "all"]
    for row in rows[:3]:
        g = int(row[1])
        mine = [i for i, grp in enumerate(curve["group"]) if grp == g]
        mean = lambda key, mine=mine: sum(curve[key][i] for i in mine) / len(mine)
        before = [curve["error_before"][i] - mean("error_before") for i in mine]  # the group's own mean removed
        after = [curve["error_after"][i] - mean("error_after") for i in mine]
        rms = lambda v: math.sqrt(sum(x * x for x in v) / len(v))
        assert row[2] == str(len(mine))
        assert row[3:7] == [f"{rms(before) / ARCSEC:.2f}", f"{max(map(abs, before)) / ARCSEC:.2f}",
                            f"{rms(after) / ARCSEC:.2f}", f"{max(map(abs, after)) / ARCSEC:.2f}"]
        assert row[7:9] == ["—", "—"]  # no held-out figures in a run stored without them: not the in-sample ones
    truth = Tables(html).find("Reference − true, per group")
    data = run["results"]["data"]["c"]
    diffs = [e["reference"] - e["true"] for e in data if e["group"] == 1]
    g1 = next(r for r in truth if r[:2] == ["c", "1"])
    assert g1[3] == f"{sum(diffs) / len(diffs) / ARCSEC + 0.0:.1f}"
    assert "error before" in html and "error after, in-sample" in html


def test_calibration_report_shows_stored_held_out_figures(tmp_path):
    run, samples, events = fake_run(tmp_path, "angle_calibration", repeats=2, axes="[z]")
    run = as_stored_by_older_code(run)
    results = run["results"]
    results["evaluation"] = {"method_in_force": {"c": "csf"}, "scheme_note": "held out", "rows": [
        {"component": "c", "method": "csf", "scheme": "leave-one-point-out", "rms": 0.6 * ARCSEC,
         "max_abs": 1.5 * ARCSEC, "end_rms": 0.7 * ARCSEC, "noise_floor": 0.5 * ARCSEC, "n_heldout": 117,
         "in_force": True},
        {"component": "c", "method": "csf", "scheme": "leave-one-group-out", "rms": 0.55 * ARCSEC,
         "max_abs": 1.2 * ARCSEC, "end_rms": 0.6 * ARCSEC, "noise_floor": 0.5 * ARCSEC, "n_heldout": 54,
         "in_force": True},
        {"component": "c", "method": "polynomial", "scheme": "leave-one-point-out", "rms": 1.4 * ARCSEC,
         "max_abs": 3.0 * ARCSEC, "end_rms": 1.0 * ARCSEC, "noise_floor": 0.5 * ARCSEC, "n_heldout": 117,
         "in_force": False}]}
    results["residual_uncertainty"] = {"c": {"value": 0.58 * ARCSEC, "expanded_uncertainty": 0.1 * ARCSEC,
                                             "coverage_factor": 2, "confidence_interval": [0.5 * ARCSEC, 0.7 * ARCSEC],
                                             "true": None, "unit": "rad", "budget": None}}
    stat = lambda rms, mx, n: {"rms": rms * ARCSEC, "max_abs": mx * ARCSEC, "n": n}
    results["before_after"] = {"c": {"datum_removed": True, "held_out_scheme": "leave-one-point-out", "groups": {
        "0": {"n": 18, "before": stat(7.0, 10.0, 18), "after_in_sample": stat(0.3, 0.6, 18),
              "after_held_out": stat(0.62, 1.4, 14)}},
        "all": {"before": stat(7.1, 10.1, 54), "after_in_sample": stat(0.31, 0.7, 54),
                "after_held_out": stat(0.6, 1.5, 42)}}}
    html = render_report(run, samples, events)
    tables = Tables(html)
    rows = {r[1]: r for r in tables.find("Error = measured − reference") if r and r[0] == "c"}
    assert rows["0"][3:9] == ["7.00", "10.00", "0.30", "0.60", "0.62", "1.40"]
    assert rows["all"][3:9] == ["7.10", "10.10", "0.31", "0.70", "0.60", "1.50"]
    kept = rows_by_label(tables.find("The method in force"))
    assert kept["c"][1:] == ["csf", "0.58 ± 0.10\n[0.50, 0.70]", "1.50", "117", "0.55", "1.20", "0.50", "″"]
    compare = rows_by_label(tables.find("All methods evaluated"))
    assert compare["component"][1:] == ["csf", "polynomial"] and compare["c (″)"][1:] == ["0.60 / 0.55", "1.40 / —"]
    assert "<pre>" not in html[: html.index("id=appendix")]  # the fit summary is a table, not raw JSON


def test_exports(tmp_path):
    run, samples, events = fake_run(tmp_path, "iso9283_repeatability", cycles=2)
    rows = list(csv.DictReader(io.StringIO(export_csv(samples))))
    assert len(rows) == len(samples) == 15
    assert float(rows[3]["solved_x_m"]) == pytest.approx(samples[3].solved.pose[0])
    assert rows[0]["step_key"] == "transform/c000/P1"
    data = json.loads(export_json(run, samples, events))
    assert data["run"]["id"] == run["id"] and len(data["samples"]) == 15
    assert data["samples"][0]["commanded"]["tcp_pose"] == list(samples[0].commanded.tcp_pose)


def test_u_has_two_significant_digits_and_the_value_the_same_decimal_place():
    from procedures.report import MICROMETRES, Figure, figure_cell

    assert figure_cell(Figure(1.36123e-6, 0.0043e-6), MICROMETRES) == (
        "<td><span class=v>1.3612</span> <span class=u>± 0.0043</span></td>")
    assert figure_cell(Figure(38.274e-6, 1.43e-6), MICROMETRES).startswith(
        "<td><span class=v>38.27</span> <span class=u>± 1.43</span>")  # never fewer decimals than the unit's
    assert figure_cell(Figure(None), MICROMETRES) == "<td>—</td>"
