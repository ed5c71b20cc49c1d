"""System tests: every procedure end to end on the simulated cell, through the real client
libraries (ur_rtde, pypylon's emulator, pymodbus, python-can), compared with the twins' truth.

One cell serves the whole module. The two calibrations run once, with small grids on every axis
(their records are what the ISO run compensates with and takes its uncertainty budget from); the
ISO test runs the paper's 30 cycles and compares the measured repeatability with the repeatability
of the true poses the twins attained, and each figure's expanded uncertainty with its error.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from instrument import ARCSEC
from instrument.compensation import CalibrationRecord
from instrument.uncertainty import coverage_study
from procedures.engine import open_engine, resolve_procedure_path
from procedures.kinds.iso import coverage_case
from sim_devices.cell import STATIC_ROBOT, SimCell

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    directory = tmp_path_factory.mktemp("cell")
    with SimCell(seed=7, directory=directory, time_scale=16.0, config={"robot": STATIC_ROBOT}) as running:
        yield running


def _procedure(tmp_path: Path, name: str, **overrides) -> Path:
    data = yaml.safe_load(resolve_procedure_path(name).read_text(encoding="utf-8"))
    data["parameters"].update(overrides)
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def _run(runs: Path, procedure: Path, station: Path) -> dict:
    with open_engine(runs, procedure=procedure, station=station) as engine:
        state = engine.execute()
        run = engine.store.get_run(engine.run_id)
        samples = engine.store.samples(engine.run_id)
    assert state == "FINISHED", run["reason"]
    assert all(s.ok for s in samples), [s.error for s in samples if not s.ok]
    return run


@pytest.fixture(scope="module")
def calibrations(cell, tmp_path_factory):
    """The displacement (x, y, z: 10 mm steps) and angle (a, b, c: 0.5° steps) calibrations, 2 repeats
    in 2 groups (the procedures' default is 3; two already give each curve a second start pose)."""
    tmp_path = tmp_path_factory.mktemp("calibrations")
    displacement = _run(tmp_path / "runs", _procedure(
        tmp_path, "displacement_calibration", step_mm=10.0, repeats=2, settle_time_s=0.05,
        interferometer_average_s=0.05, frames_per_pose=1, groups=2,
        group_start_offsets_mm=[[0.0, 0.0, 0.0], [0.5, 0.5, 0.5]]), cell.station_path)
    angle = _run(tmp_path / "runs", _procedure(tmp_path, "angle_calibration", step_deg=0.5, repeats=2,
                                               settle_time_s=0.05, frames_per_pose=1, table_speed_deg_s=20.0,
                                               groups=2, group_start_offsets_deg=[0.0, 0.1]),
                 cell.station_path)
    return {"displacement": displacement, "angle": angle, "tmp": tmp_path}


@pytest.mark.timeout(600)
def test_displacement_calibration_measures_real_errors_and_fits_them(calibrations):
    run = calibrations["displacement"]
    data = run["results"]["data"]
    record = CalibrationRecord.from_json(Path(run["results"]["record_path"]).read_text(encoding="utf-8"))
    for axis in ("x", "z"):
        rows = data[axis]
        assert len(rows) == 8 * 2 * 2  # 8 points (0..70 mm), 2 repeats, 2 groups
        reference, true, measured, groups, points = (np.array([r[key] for r in rows])
                                                     for key in ("reference", "true", "measured", "group", "point"))
        # The interferometer agrees with the world's true displacement to well under a µm after
        # removing each group's datum (its reference is the group's nominal start plus the reading).
        for g in np.unique(groups):
            offset = np.median((reference - true)[groups == g])
            assert np.max(np.abs((reference - true)[groups == g] - offset)) < 0.5e-6
        # Before compensation the instrument is off by tens of µm (nominal ≠ true geometry) ...
        raw = measured - reference
        assert 5e-6 < np.max(np.abs(raw - np.median(raw))) < 300e-6
        # ... and the record's compensation removes that error on the calibration data, down to the
        # noise floor: the scatter of repeats at one point (per-frame speckle noise, ~1-2 µm), which
        # no compensation can remove. Each group keeps its own datum offset in the corrected data,
        # so compare the shapes within groups.
        residual = record.correct(axis, measured).corrected - reference
        for g in np.unique(groups):
            residual[groups == g] -= residual[groups == g].mean()
        cells = [raw[(groups == g) & (points == k)] for g in np.unique(groups) for k in np.unique(points)]
        floor = np.sqrt(np.mean([np.var(c, ddof=1) for c in cells]))
        print(f"{axis}: raw std {np.std(raw) * 1e6:.2f} µm, residual {np.std(residual) * 1e6:.2f} µm, "
              f"repeat floor {floor * 1e6:.2f} µm")
        assert np.std(residual) < 1.75 * floor  # the floor from 16 two-repeat cells is known to ±18 %
        assert np.std(residual) < 0.5 * np.std(raw)
        assert np.std(residual) < 3e-6


@pytest.mark.timeout(600)
def test_angle_calibration_uses_the_table_as_reference(cell, calibrations):
    run = calibrations["angle"]
    rows = run["results"]["data"]["b"]
    assert len(rows) == 5 * 2 * 2
    reference = np.array([r["reference"] for r in rows])
    true = np.array([r["true"] for r in rows])
    measured = np.array([r["measured"] for r in rows])
    # The table's encoder is within its ±0.5″ class of the true angle.
    assert np.max(np.abs(reference - true)) < 0.6 * ARCSEC
    # The raw instrument is off by arc-seconds to tens of arc-seconds over ±1°.
    assert 1 * ARCSEC < np.max(np.abs(measured - reference)) < 200 * ARCSEC
    assert Path(run["results"]["record_path"]).is_file()
    assert cell.control("ping") == "pong"
    # The OPR went back on the robot at the end of the run.
    assert cell.control("describe")["world"]  # the cell is still healthy


@pytest.fixture(scope="module")
def iso_run(cell, calibrations):
    """30 cycles with both records in force."""
    tmp_path = calibrations["tmp"]
    station = yaml.safe_load(cell.station_path.read_text(encoding="utf-8"))
    station["calibration"] = {"record": [calibrations["displacement"]["results"]["record_path"],
                                         calibrations["angle"]["results"]["record_path"]]}
    calibrated = tmp_path / "station-calibrated.yaml"
    calibrated.write_text(yaml.safe_dump(station), encoding="utf-8")
    procedure = _procedure(tmp_path, "iso9283_repeatability", cycles=30, settle_time_s=0.05, frames_per_pose=1,
                           payload_mass_kg=1.2, uncertainty_draws=500)
    return _run(tmp_path / "runs", procedure, calibrated), station


@pytest.mark.timeout(900)
def test_iso_repeatability_agrees_with_the_twins_truth(iso_run):
    """30 cycles over P1..P5: measured RP within the instrument's stated accuracy of the truth."""
    run, _ = iso_run
    results = run["results"]
    assert results["order"] == ["P1", "P5", "P4", "P3", "P2"]
    differences = {"l": [], "a": [], "b": [], "c": []}
    for point in results["order"]:
        measured, true = results["points"][point]["stats"], results["points"][point]["true_stats"]
        assert measured["n"] == true["n"] == 30
        # The twin's repeatability is ~10 µm and ~0.001° per axis: RP_l ≈ 35 µm, RP_a ≈ 11″.
        assert 15e-6 < true["rp_l"] < 60e-6
        differences["l"].append(abs(measured["rp_l"] - true["rp_l"]))
        for k in "abc":
            differences[k].append(abs(measured[f"rp_{k}"] - true[f"rp_{k}"]))
        # The confidence interval brackets the measured value.
        low, high = measured["rp_l_ci"]
        assert low <= measured["rp_l"] <= high
    print(json.dumps({k: np.round(np.array(v) / (1e-6 if k == "l" else ARCSEC), 2).tolist()
                      for k, v in differences.items()}))
    # The instrument's stated accuracy (the paper's claim): RP within 1.5 µm and 2″ of the
    # reference. Per-frame noise is ~1.1 µm and ~1.1″ per component; with n = 30 it moves one
    # point's RP by ~0.5 µm / ~0.6″ (1σ), so the claim is checked on the RMS over the five points,
    # and each single point against twice the claim (a gross error, not noise, would break that).
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in differences.items()}
    assert rms["l"] < 1.5e-6
    assert max(differences["l"]) < 3.0e-6
    for k in "abc":
        assert rms[k] < 2.0 * ARCSEC
        assert max(differences[k]) < 4.0 * ARCSEC


@pytest.mark.timeout(900)
def test_iso_uncertainty_covers_the_twins_truth(iso_run):
    """U (k = 2) of the figures the budget can see covers their error; the rest is flagged.

    The calibrations tie neither the position frame's squareness nor its rotation to the angle frame
    (docs/uncertainty.md, "On the simulated cell"): without a stated squareness the run says U leaves
    it out, and AP and AD are not checked here. With one stated, U covers the large majority of every
    figure.
    """
    run, station = iso_run
    results = run["results"]
    uncertainty = results["uncertainty"]
    assert uncertainty["evaluated"], uncertainty["reason"]
    assert "frame_squareness_not_stated" in {d["code"] for d in results["deviations"]}
    seen = {"rp": [], "drift": [], "rd": []}
    for group in ("points", "distances"):
        for figures in results["figures"][group].values():
            for name, figure in figures.items():
                family = "rp" if name.startswith("rp_") else "drift" if name[:3] in ("dap", "drp") else \
                    "rd" if name.startswith("rd_") else None
                if family:
                    seen[family].append(abs(figure["value"] - figure["true"]) <= figure["expanded_uncertainty"])
    print({family: f"{sum(v)}/{len(v)}" for family, v in seen.items()})
    assert len(seen["rp"]) == 20 and len(seen["drift"]) == 40 and len(seen["rd"]) == 7
    assert sum(seen["rp"]) >= 18  # 95 % of 20; one or two misses are chance
    assert sum(seen["drift"]) + sum(seen["rd"]) >= 0.85 * 47
    stated = coverage_study([coverage_case(results, station["frames"]["tool_in_opr"], frame_squareness=500e-6)],
                            draws=300)
    covered = sum(r.coverage * r.count for r in stated.rows)
    total = sum(r.count for r in stated.rows)
    print(f"with 500 µrad of frame squareness stated: {covered:.0f}/{total} figures covered")
    assert covered >= 0.85 * total


@pytest.mark.timeout(900)
def test_iso_records_the_cells_test_conditions(iso_run, cell):
    run, _ = iso_run
    conditions = run["results"]["test_conditions"]
    assert conditions["robot"]["manufacturer"] == "Universal Robots" and conditions["robot"]["serial_number"]
    assert conditions["payload"]["mass_kg"] == 1.2 and conditions["payload"]["set_on_robot"]
    environment = conditions["environment"]  # from the interferometer twin's environmental unit
    assert environment["readings"] == 5 + 30 * 5
    assert 288 < environment["mean"]["air_temperature_k"] < 298 and 90e3 < environment["mean"]["pressure_pa"] < 110e3
    assert abs(environment["drift"]["air_temperature_k"]) < 0.5
    assert {r["applied"] for r in conditions["measurement_system"]["calibration_records"]} == {True}
