"""The pieces of the ISO budget and the test conditions, each against a value worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from instrument import ARCSEC
from instrument.environment import AirConditions
from instrument.uncertainty import Correlation
from procedures.kinds import environment_summary, pose_directions, scale_uncertainty
from procedures.kinds.calibration import before_after, off_axis_slopes
from procedures.kinds.iso import (
    BudgetUnavailable,
    environment_scale_term,
    iso_budget,
    largest_cube_edge,
    off_axis_error,
    squareness_terms,
)
from procedures.station import StationFile
from tests.fakes import station_dict


def test_pose_directions_are_the_signs_of_the_move():
    assert pose_directions(None, [1, 2, 3, 0, 0, 0]) == dict.fromkeys("xyzabc")
    directions = pose_directions([0.0, 0.01, 0.02, 0.0, 0.0, 3.1], [0.01, 0.01, 0.0, 2e-6, 0.0, -3.1])
    # c wraps through ±π: from 3.1 to −3.1 rad is +0.083 rad, approached from below.
    assert directions == {"x": 1, "y": None, "z": -1, "a": 1, "b": None, "c": 1}


def test_off_axis_slopes_recover_a_known_cross_axis_error():
    rng = np.random.default_rng(0)
    lines = {}
    for axis, k in (("x", 0), ("y", 1)):
        samples = []
        for key in range(3):
            for value in np.linspace(0, 0.07, 8):
                pose = rng.normal(0, 1e-7, 6)
                pose[k] += value
                pose[3] += (400 * ARCSEC if axis == "x" else -200 * ARCSEC) * value  # ″ per m
                pose[2] += 5e-4 * value
                samples.append((key, pose.tolist()))
        lines[axis] = samples
    found = off_axis_slopes(lines)
    assert found["lines"] == {"x": 3, "y": 3}
    assert found["slopes"]["x"]["a"] == pytest.approx(400 * ARCSEC, rel=0.01)
    assert found["slopes"]["y"]["a"] == pytest.approx(-200 * ARCSEC, rel=0.01)
    assert found["slopes"]["x"]["z"] == pytest.approx(5e-4, rel=0.01)
    error = off_axis_error({"x": {"a": 400 * ARCSEC}, "y": {"a": -200 * ARCSEC}}, [0.05, 0.02, 0.0])
    assert error[3] / ARCSEC == pytest.approx(400 * 0.05 - 200 * 0.02)
    assert off_axis_slopes({"x": [(0, [0.0] * 6)]}) is None  # one point on a line: no slope


def test_before_after_removes_each_groups_datum():
    curves = {"x": {"group": [0, 0, 1, 1], "error_before_datum_removed": [1e-6, -1e-6, 2e-6, -2e-6],
                    "error_after_datum_removed": [0.0, 0.0, 0.0, 0.0],
                    "error_after_held_out": [None, 1e-7, None, 2e-7]}}
    summary = before_after(curves)["x"]
    assert summary["groups"]["1"]["before"] == {"rms": pytest.approx(2e-6), "max_abs": 2e-6, "n": 2}
    assert summary["all"]["after_held_out"]["n"] == 2  # the end points are never held out


def test_environment_summary_start_end_drift():
    readings = [{"timestamp": t, "air_temperature_k": 293.15 + 0.01 * t, "pressure_pa": 101000.0 - t,
                 "relative_humidity": 0.4, "material_temperatures_k": [293.0, None, None]} for t in (10.0, 0.0, 5.0)]
    summary = environment_summary(readings)
    assert summary["start"]["time"] == 0.0 and summary["end"]["time"] == 10.0
    assert summary["drift"]["air_temperature_k"] == pytest.approx(0.1)
    assert summary["drift"]["pressure_pa"] == pytest.approx(-10.0)
    assert summary["drift"]["material_temperatures_k"] == [0.0, None, None]
    assert summary["mean"]["pressure_pa"] == pytest.approx(100995.0)
    assert environment_summary([]) is None


def test_scale_uncertainty_from_the_sensors_specification():
    # Sensitivities near 20 °C (docs/environment.md): 0.955e-6 /K, 0.268e-6 /hPa, 0.0085e-6 per % RH.
    expected = math.sqrt((0.955e-6 * 0.2) ** 2 + (0.268e-6 * 1.0) ** 2 + (0.0085e-6 * 6) ** 2) / math.sqrt(3)
    found = scale_uncertainty(AirConditions(293.15, 101325.0, 0.5, 400.0), 632.991e-9)
    assert found == pytest.approx(expected, rel=0.05)
    assert scale_uncertainty(None, 632.991e-9, compensated=False) > 5 * found


def test_largest_cube_edge_in_the_envelope():
    station = StationFile.model_validate(yaml.safe_load(yaml.safe_dump(station_dict())))
    # Box 0.5 × 0.6 × 0.4 m, M's axes along the base's (the reference is flipped about x): 0.4 m.
    assert largest_cube_edge(station) == pytest.approx(0.4)
    tilted = station_dict()
    tilted["frames"]["reference_tcp_pose"] = [0.45, -0.10, 0.27, 0.0, 0.0, math.pi / 4]  # M turned 45° about z
    assert largest_cube_edge(StationFile.model_validate(tilted)) == pytest.approx(0.5 / math.sqrt(2))


def test_environment_term_is_a_thermal_scale():
    known = environment_scale_term(293.65, 293.15)
    assert known.correlation is Correlation.SCALE and known.shared
    expected = 23e-6 * math.sqrt(0.5**2 / 3 + 2 * (0.2 / math.sqrt(3)) ** 2)
    assert known.standard_uncertainty[0] == pytest.approx(expected)
    assert environment_scale_term(None, 293.15).standard_uncertainty[0] == pytest.approx(23e-6 / math.sqrt(3))


def test_squareness_terms_shear_the_points_and_rotate_the_fit():
    positions = {"P1": [0.0, 0.0, 0.0], "P2": [0.03, 0.0, 0.0], "P3": [0.0, 0.03, 0.0]}
    shear, rotation = squareness_terms(1e-4, positions, lever=0.02, transform=True)
    spread = math.sqrt(np.mean([np.sum((np.array(p) - np.mean(list(positions.values()), axis=0)) ** 2)
                                for p in positions.values()]))
    assert shear.correlation is Correlation.POINT and shear.standard_uncertainty[0] == pytest.approx(1e-4 * spread)
    assert rotation.correlation is Correlation.RUN and rotation.standard_uncertainty == pytest.approx(
        (2e-6,) * 3 + (1e-4,) * 3)
    assert squareness_terms(0.0, positions, lever=0.02, transform=True) == []


def _info(components, floor, extra=None):
    evaluation = {c: {"method": "csf", "heldout_rms": 2 * floor, "heldout_max": 4 * floor, "noise_floor": floor,
                      "n_heldout": 117, "group_heldout_rms": floor, "uncompensated_rms": 50 * floor, "n_points": 15,
                      "n_observations": 135, "n_groups": 3, "directions": []} for c in components}
    return {"id": "sha256:" + "".join(components), "components": list(components),
            "validity": dict.fromkeys(components, [0.0, 0.07]), "evaluation": evaluation,
            "references": [extra] if extra else [], "temperature_c": 20.0}


def test_iso_budget_from_records():
    displacement = _info("xyz", 1e-6, {"instrument": "laser interferometer", "scale_standard_uncertainty": 2e-7,
                                       "reading_noise_m": 1e-8, "frames_per_pose": 3})
    angle = _info("abc", 5e-6)
    positions = {"P1": [0.035] * 3, "P2": [0.007] * 3}
    budget, estimator, off_axis = iso_budget([displacement, angle], {"x", "y", "z", "a", "b", "c"},
                                             frames_per_pose=1, per_frame=None,
                                             transform={"points": 5, "spread": 0.04, "lever": 0.04},
                                             run_air_k=293.65, positions=positions)
    terms = {t.name: t for t in budget.terms}
    # The run averages 1 frame, the calibration 3: its floor × √3. dof = 135 − 15 × 3 = 90.
    assert terms["frame noise"].standard_uncertainty[0] == pytest.approx(1e-6 * math.sqrt(3))
    assert terms["frame noise"].dof == 90
    # Held-out RMS 2 µm less the 1 µm floor in quadrature.
    assert terms["compensation residual"].standard_uncertainty[0] == pytest.approx(math.sqrt(3) * 1e-6)
    assert terms["compensation residual"].correlation_length[0] == pytest.approx(0.005)
    assert terms["interferometer scale"].standard_uncertainty[0] == 2e-7
    assert off_axis is None and "off-axis angle error" not in terms  # the record states no slopes
    assert estimator["records"] == sorted([displacement["id"], angle["id"]])
    # Not compensated: the record's raw error is the systematic term.
    budget, _, _ = iso_budget([displacement, angle], set(), frames_per_pose=1, per_frame=None, transform=None,
                              run_air_k=None, positions=positions)
    assert {t.name: t for t in budget.terms}["compensation residual"].standard_uncertainty[3] == pytest.approx(2.5e-4)
    with pytest.raises(BudgetUnavailable, match="noise floor of a, b, c"):
        iso_budget([displacement], {"x"}, frames_per_pose=1, per_frame=None, transform=None, run_air_k=None,
                   positions=positions)
