"""Issue 13's data side and issue 14's procedure side on the fake cell, with the real compensation.

The fake cell's instrument error is a smooth function of each component's own value (no off-axis
error), its noise and the robot's scatter are known, and its truth log gives the true poses: so the
calibration records are real ``instrument.compensation`` records, the ISO run's U is evaluated from
them, and both can be checked against the truth. Also: test conditions, deviations, approach
directions, the interferometer's wavelength compensation, the export, and the runs stored by older code.
"""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import numpy as np
import pytest
import yaml

from instrument.environment import AirConditions, wavelength_compensation_factor
from procedures.cli import main
from procedures.engine import open_engine
from procedures.station import InstrumentScience
from procedures.store import RunStore
from tests.fakes import FakeCell, FakeScience, station_dict

# The module's shared runs (two calibrations and an 8-cycle ISO run with 300 uncertainty draws, all CPU)
# took 134 s in a loaded make test and over 180 s in another: the first test that sets them up needs more.
pytestmark = pytest.mark.timeout(480)

FIGURE_KEYS = {"value", "expanded_uncertainty", "coverage_factor", "confidence_interval", "true"}


class RecordScience(FakeScience):
    """The fake cell's measurements, the real calibration fit and records."""

    def fit_calibration(self, kind, data, provenance):
        return InstrumentScience().fit_calibration(kind, data, provenance)

    def load_compensator(self, path):
        return InstrumentScience().load_compensator(path)


def _run(tmp_path: Path, cell: FakeCell, kind: str, station: Path, **params) -> dict:
    procedure = tmp_path / f"{kind}.yaml"
    procedure.write_text(yaml.safe_dump({"procedure": kind, "parameters": {"settle_time_s": 0, "frames_per_pose": 1,
                                                                             **params}}), encoding="utf-8")
    with open_engine(tmp_path / "runs", procedure=procedure, station=station, science=RecordScience(cell),
                     devices=cell.devices(), operator=cell.operator) as engine:
        state = engine.execute()
        run = engine.store.get_run(engine.run_id)
        run["samples"] = engine.store.samples(engine.run_id)
    assert state == "FINISHED", run["reason"]
    return run


def _station(tmp_path: Path, truth: Path, name: str = "station.yaml", **overrides) -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(station_dict(truth_log=str(truth), **overrides)), encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A displacement (both directions) and an angle calibration (one) on the fake cell, and an ISO run
    with both records in force."""
    tmp_path = tmp_path_factory.mktemp("calibrated")
    truth = tmp_path / "truth.jsonl"
    cell = FakeCell(seed=5, truth_log=truth)
    station = _station(tmp_path, truth)
    displacement = _run(tmp_path, cell, "displacement_calibration", station, repeats=2, step_mm=10.0,
                        approach="both")
    angle = _run(tmp_path, cell, "angle_calibration", station, repeats=2)
    records = [displacement["results"]["record_path"], angle["results"]["record_path"]]
    in_force = _station(tmp_path, truth, "calibrated.yaml", calibration={"record": records},
                        rated={"speed": 1.0, "payload": 5.0})
    iso = _run(tmp_path, cell, "iso9283_repeatability", in_force, cycles=8, payload_mass_kg=5.0,
               payload_cog_m=[0.0, 0.0, 0.04], warm_up="run", warm_up_s=0.02, operator="A. Tester",
               uncertainty_draws=300)
    return {"tmp": tmp_path, "cell": cell, "displacement": displacement, "angle": angle, "iso": iso}


def test_iso_uncertainty_covers_the_fake_truth(calibrated):
    results = calibrated["iso"]["results"]
    assert results["uncertainty"]["evaluated"], results["uncertainty"]["reason"]
    names = {t["name"] for t in results["uncertainty"]["budget"]["terms"]}
    assert {"frame noise", "compensation residual", "interferometer scale", "rotary table encoder",
            "transform fit", "environment", "off-axis angle error"} <= names
    covered, total = 0, 0
    for group in ("points", "distances"):
        for figures in results["figures"][group].values():
            for figure in figures.values():
                assert FIGURE_KEYS <= set(figure) and figure["coverage_factor"] == 2
                assert figure["true"] is not None and figure["expanded_uncertainty"] > 0
                total += 1
                covered += abs(figure["value"] - figure["true"]) <= figure["expanded_uncertainty"]
    # 8 cycles, 5 points: RP, AP and drift per point, AD/RD for P2-P4. k = 2 promises about 95 %.
    assert total == 5 * 19 + 14
    assert covered / total >= 0.85, f"{covered}/{total} covered"
    estimator = results["uncertainty"]["noise_estimator"]
    assert estimator["used"] == "calibration noise floor" and len(estimator["records"]) == 2
    # The fake's frame noise is 0.3 µm and 0.1 µrad (+ the references'): the floor finds it.
    u = estimator["standard_uncertainty"]
    assert 0.2e-6 < u["x"] < 0.6e-6 and u["a"] < 2e-6


def test_iso_records_its_test_conditions(calibrated):
    cell, results = calibrated["cell"], calibrated["iso"]["results"]
    conditions = results["test_conditions"]
    assert conditions["robot"] == {"manufacturer": "Universal Robots", "model": "UR5", "serial_number": "20235500123",
                                   "controller_version": "5.15.0.0", "source": "controller"}
    assert conditions["payload"] | {} == {"mass_kg": 5.0, "cog_m": [0.0, 0.0, 0.04], "set_on_robot": True,
                                          "rated_mass_kg": 5.0, "percent_of_rated": 100.0}
    assert cell.robot.payload[0] == 5.0 and list(cell.robot.payload[1]) == [0.0, 0.0, 0.04]
    motion = conditions["motion"]  # 50 % of the envelope's 0.5 m/s and 2 m/s²
    assert motion["speed_mm_s"] == pytest.approx(250.0) and motion["acceleration_mm_s2"] == pytest.approx(1000.0)
    assert motion["percent_of_rated_speed"] == pytest.approx(25.0)
    assert conditions["operator"] == {"name": "A. Tester", "source": "procedure"}
    assert conditions["warm_up"]["mode"] == "run" and conditions["warm_up"]["moves"] >= 1
    assert conditions["cycles"] == {"planned": 8, "measured": dict.fromkeys(["P1", "P5", "P4", "P3", "P2"], 8)}
    cube = conditions["cube"]
    assert cube["edge_m"] == 0.07 and cube["largest_edge_m"] == pytest.approx(0.4)  # the fake envelope's y span
    p1 = cube["points"]["P1"]
    assert p1["in_m"] == pytest.approx([0.035] * 3)
    assert np.allclose(p1["in_base"][:3], [0.45 + 0.035, -0.10 - 0.035, 0.27 - 0.035])  # reference flipped about x
    environment = conditions["environment"]
    assert environment["readings"] == 5 + 8 * 5 and environment["start"]["air_temperature_k"] == 301.15
    assert environment["drift"]["air_temperature_k"] == 0.0
    records = conditions["measurement_system"]["calibration_records"]
    assert [r["applied"] for r in records] == [True, True] and records[0]["bidirectional"]
    codes = {d["code"] for d in results["deviations"]}
    assert "cycles_below_30" in codes and "cube_not_largest" in codes and "speed_not_rated" in codes
    assert "payload_not_rated" not in codes and "no_compensation" not in codes


def test_directions_reach_the_records_and_a_one_directional_angle_record_is_flagged(calibrated):
    displacement = calibrated["displacement"]
    directions = {s.meta["approach"] for s in displacement["samples"]}
    assert directions == {1, -1}
    assert all(row["direction"] in (1, -1) for rows in displacement["results"]["data"].values() for row in rows)
    records = calibrated["iso"]["results"]["test_conditions"]["measurement_system"]["calibration_records"]
    assert records[0]["approach_directions"] == {c: [-1, 1] for c in "xyz"}
    assert records[1]["approach_directions"] == {c: [1] for c in "abc"}
    # The ISO cycle approaches P1 from below in x, y and z; its angles do not move (no direction).
    approach = calibrated["iso"]["results"]["points"]["P1"]["approach"]
    assert approach == {"x": 1, "y": 1, "z": 1, "a": None, "b": None, "c": None}
    iso_samples = [s for s in calibrated["iso"]["samples"] if s.phase == "iso"]
    assert all(s.corrected.direction == s.reference.approach for s in iso_samples)
    # Angles never move, and the displacement record is bidirectional: nothing uncovered.
    assert "direction_not_covered" not in {d["code"] for d in calibrated["iso"]["results"]["deviations"]}


def test_every_displacement_point_is_approached_from_the_planned_side(tmp_path):
    cell = FakeCell(seed=1)
    targets = []
    original = cell.robot.move_linear

    def recording(pose, *args, **kwargs):
        targets.append(np.asarray(pose, dtype=float).copy())
        return original(pose, *args, **kwargs)

    cell.robot.move_linear = recording
    run = _run(tmp_path, cell, "displacement_calibration", _station(tmp_path, tmp_path / "t.jsonl"), axes=["y"],
               repeats=2, approach="both", overshoot_mm=2.0)
    moves = iter(targets)
    previous = None
    by_pose = {tuple(np.round(t, 9)): t for t in targets}
    assert by_pose
    for sample in run["samples"]:
        target = np.asarray(sample.commanded.tcp_pose)
        # The move before the sample's target along M's y (= −y of the base: the reference is flipped about x).
        while True:
            move = next(moves)
            if np.allclose(move, target):
                break
            previous = move
        assert previous is not None
        along = -(target[1] - previous[1])
        assert np.sign(along) == sample.meta["approach"], sample.step_key


def test_displacement_reference_is_compensated_for_the_air(tmp_path):
    cell = FakeCell(seed=3, truth_log=tmp_path / "truth.jsonl")
    run = _run(tmp_path, cell, "displacement_calibration", _station(tmp_path, tmp_path / "truth.jsonl"),
               axes=["x"], repeats=2)
    factor = wavelength_compensation_factor(AirConditions(301.15, 92_000.0, 0.3, 400.0), wavelength_m=632.991e-9)
    assert factor - 1 == pytest.approx(31.5e-6, rel=0.02)  # docs/environment.md: 28 °C, 92 kPa, 30 % RH
    far = [s for s in run["samples"] if s.meta["point"] == max(x.meta["point"] for x in run["samples"])]
    for sample in far:
        readings, environment = sample.reference.readings, sample.reference.environment
        assert readings["wavelength_compensation"]["factor"] == pytest.approx(factor)
        assert readings["interferometer_m"] == pytest.approx(readings["interferometer_raw_m"] * factor)
        assert environment is not None and environment["air_temperature_k"] == 301.15
        assert environment["material_temperatures_k"] == [301.35, None, None]
    rows = run["results"]["data"]["x"]
    for g in {r["group"] for r in rows}:
        mine = [r for r in rows if r["group"] == g]
        d = np.array([r["reference"] - r["true"] for r in mine])
        assert np.max(np.abs(d - d.mean())) < 0.5e-6  # compensated: true to the fake head's noise
    raw_error = [s.reference.readings["interferometer_raw_m"] - s.reference.readings["interferometer_m"] for s in far]
    assert min(abs(e) for e in raw_error) > 1.5e-6  # uncompensated, 70 mm read 2.2 µm short
    conditions = run["results"]["test_conditions"]
    assert conditions["wavelength_compensation"]["factor_mean"] == pytest.approx(factor)
    assert conditions["reference"]["scale_standard_uncertainty"] < 0.5e-6


def test_an_environmental_feed_gap_is_read_again_and_a_sensor_fault_fails_the_run(tmp_path):
    cell = FakeCell(seed=4)
    cell.environment_gaps = {2}
    run = _run(tmp_path, cell, "displacement_calibration", _station(tmp_path, tmp_path / "t.jsonl"), axes=["z"],
               repeats=2, retry_backoff_s=0)
    assert all(s.reference.environment is not None for s in run["samples"])
    cell.environment_faults = {cell.environment_reads + 3}
    procedure = tmp_path / "again.yaml"
    procedure.write_text("procedure: displacement_calibration\nparameters: {axes: [z], repeats: 2, settle_time_s: 0, "
                         "frames_per_pose: 1}\n", encoding="utf-8")
    with open_engine(tmp_path / "runs", procedure=procedure, station=_station(tmp_path, tmp_path / "t.jsonl"),
                     science=RecordScience(cell), devices=cell.devices(), operator=cell.operator) as engine:
        assert engine.execute() == "FAILED"
        reason = engine.store.get_run(engine.run_id)["reason"]
    assert reason.startswith("interferometer: environment failed: sensor fault")


def test_calibration_results_are_honest(calibrated):
    results = calibrated["displacement"]["results"]
    evaluation = results["evaluation"]
    in_force = [r for r in evaluation["rows"] if r["in_force"]]
    assert {r["component"] for r in in_force} == {"x", "y", "z"}
    assert {r["scheme"] for r in in_force} == {"leave-one-point-out", "leave-one-group-out"}
    for component, summary in results["before_after"].items():
        held = summary["all"]["after_held_out"]
        lopo = next(r for r in in_force if r["component"] == component and r["scheme"] == "leave-one-point-out")
        # The held-out residuals are the record's own leave-one-point-out evaluation.
        assert held["rms"] == pytest.approx(lopo["rms"], rel=1e-9) and held["n"] == lopo["n_heldout"]
        # Datum removed: before is the fake's ±50 µm curve, after the noise (0.3 µm + 0.1 µm head).
        assert summary["all"]["before"]["rms"] > 10e-6
        assert summary["all"]["after_in_sample"]["rms"] < 1e-6
        assert set(summary["groups"]) == {"0", "1", "2"}
        figure = results["residual_uncertainty"][component]
        assert FIGURE_KEYS <= set(figure) and figure["unit"] == "m"
        assert abs(figure["value"] - figure["true"]) <= figure["expanded_uncertainty"] + 0.1e-6
        truth = results["reference_vs_truth"][component]
        assert truth["all"]["max_abs"] < 0.5e-6  # like with like: each group's datum offset removed
    assert results["off_axis"]["lines"] == {"x": 12, "y": 12, "z": 12}  # 3 groups × 2 repeats × 2 directions


def test_export_json_carries_figures_conditions_and_deviations(calibrated, capsys):
    runs = calibrated["tmp"] / "runs"
    run_id = calibrated["iso"]["id"]
    assert main(["export", run_id, "--json", "--runs-dir", str(runs)]) == 0
    exported = json.loads(capsys.readouterr().out)["results"]
    assert exported["schema"] == "opr-instrument-results/1" and exported["kind"] == "iso9283"
    assert set(exported["points"]) == {"P1", "P2", "P3", "P4", "P5"}
    rp = exported["points"]["P3"]["rp_l"]
    assert FIGURE_KEYS <= set(rp) and rp["budget"]["contributions"]["frame noise"] > 0
    assert set(exported["distances"]["P2-P4"]) >= {"ad_p", "rd_p"}
    assert exported["test_conditions"]["robot"]["serial_number"] == "20235500123"
    assert any(d["code"] == "cycles_below_30" for d in exported["deviations"])
    assert exported["uncertainty"]["coverage_factor"] == 2
    calibration_id = calibrated["angle"]["id"]
    assert main(["export", calibration_id, "--json", "--runs-dir", str(runs)]) == 0
    components = json.loads(capsys.readouterr().out)["results"]["components"]
    assert set(components) == {"a", "b", "c"} and components["b"]["unit"] == "rad"


def test_without_records_the_run_says_it_has_no_uncertainty(tmp_path):
    cell = FakeCell(seed=6, truth_log=tmp_path / "truth.jsonl")
    run = _run(tmp_path, cell, "iso9283_repeatability", _station(tmp_path, tmp_path / "truth.jsonl"), cycles=3)
    results = run["results"]
    assert results["uncertainty"]["evaluated"] is False
    assert "noise floor" in results["uncertainty"]["reason"]
    p1 = results["figures"]["points"]["P1"]["rp_l"]
    assert p1["expanded_uncertainty"] is None and p1["value"] == results["points"]["P1"]["stats"]["rp_l"]
    codes = {d["code"] for d in results["deviations"]}
    assert {"uncertainty_not_evaluated", "no_compensation", "payload_not_rated", "cycles_below_30"} <= codes
    assert results["test_conditions"]["payload"]["set_on_robot"] is False


FIXTURE = Path(__file__).parent / "data" / "runs_stored_by_5786d73.sql"


def test_runs_stored_by_older_code_still_export(tmp_path, capsys):
    runs = tmp_path / "runs"
    runs.mkdir()
    db = sqlite3.connect(runs / "runs.sqlite")
    db.executescript(FIXTURE.read_text(encoding="utf-8"))
    db.close()
    with RunStore(runs) as store:
        stored = [store.get_run(r["id"]) for r in store.list_runs()]
    for run in stored:
        assert main(["export", run["id"], "--json", "--runs-dir", str(runs)]) == 0
        exported = json.loads(capsys.readouterr().out)["results"]
        assert exported["stored_by"] == "older code (no uncertainty)" and exported["test_conditions"] is None
        if run["procedure"] == "iso9283_repeatability" and run["results"]:
            rp_l = exported["points"]["P1"]["rp_l"]
            assert rp_l["value"] == run["results"]["points"]["P1"]["stats"]["rp_l"]
            assert rp_l["expanded_uncertainty"] is None and rp_l["coverage_factor"] == 2
