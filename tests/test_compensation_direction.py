"""Approach direction: hysteresis recovered from bidirectional calibrations, uncovered directions reported."""

import numpy as np
import pytest

from instrument.compensation import (
    CalibrationData,
    SmoothingSplineCompensator,
    calibrate,
    hard_campaign,
    held_out_residuals,
    synthetic_calibration,
)

UM = 1e-6


def rms(r):
    return float(np.sqrt(np.mean(np.square(r))))


@pytest.fixture(scope="module")
def campaign():
    return hard_campaign(4, "x", hysteresis=True)


def test_hysteresis_is_recovered_from_a_bidirectional_calibration(campaign):
    data = campaign.calibration
    assert data.directions == (-1, 1)
    model = SmoothingSplineCompensator().fit(data)
    assert model.directions == (-1, 1) and model.hysteresis is not None
    fine = np.linspace(0.001, 0.069, 50)
    true_half = (campaign.true_error(fine, 1) - campaign.true_error(fine, -1)) / 2
    assert 1 * UM <= true_half.mean() <= 2 * UM  # 2-4 µm full difference
    # the hysteresis curve comes from 15 points x 18 observations: well under the noise of one (0.41 µm)
    assert np.abs(model.hysteresis.predict(fine) - true_half).max() < 0.2 * UM
    # mid-way prediction when the direction is unknown
    np.testing.assert_allclose(model.predict(fine), (model.predict(fine, 1) + model.predict(fine, -1)) / 2)
    # and on fresh observations from both directions the model is as good as the oracle allows
    for held in campaign.held_out:
        residual, oracle = held_out_residuals(model, held)
        assert rms(residual) < 1.3 * rms(oracle), held.kind


def test_ignoring_the_direction_leaves_the_hysteresis_in_the_residual(campaign):
    data = campaign.calibration
    blind = CalibrationData("x", data.measured, data.reference, data.group, data.point)
    model = SmoothingSplineCompensator().fit(blind)
    assert model.hysteresis is None and model.directions == ()
    residual, oracle = held_out_residuals(model, campaign.held_out[0])
    assert rms(residual) > 1.5 * rms(oracle)


def test_group_offsets_are_found_under_hysteresis(campaign):
    model = SmoothingSplineCompensator().fit(campaign.calibration)
    for g in (1, 2):
        assert model.group_offset(g) == pytest.approx(-campaign.group_offsets[g], abs=4 * campaign.noise_sigma)


def test_a_partly_bidirectional_design_still_separates_offsets_and_hysteresis():
    """Group 0 approaches from both sides, groups 1 and 2 from +1 only."""
    rng = np.random.default_rng(8)
    nominal = np.linspace(0.0, 0.07, 15)
    curve = lambda v: 30 * UM * np.sin(v / 0.03)
    half = 1.5 * UM
    parts = []
    for g, (offset, directions) in enumerate([(0.0, (-1, 1)), (20 * UM, (1,)), (-15 * UM, (1,))]):
        d = synthetic_calibration("y", nominal, curve, repeats=3, group_offsets=(offset,), measurement_noise=0.4 * UM,
                                  reference_noise=0.1 * UM, hysteresis=lambda v: np.full(np.shape(v), 2 * half),
                                  directions=directions, rng=rng)
        parts.append((d.measured, d.reference, np.full(d.measured.size, g), d.point, d.direction))
    data = CalibrationData("y", *(np.concatenate(p) for p in zip(*parts)))
    model = SmoothingSplineCompensator().fit(data)
    assert model.group_offset(1) == pytest.approx(-20 * UM, abs=0.3 * UM)
    assert model.group_offset(2) == pytest.approx(15 * UM, abs=0.3 * UM)
    fine = np.linspace(0.002, 0.068, 30)
    assert np.abs(model.hysteresis.predict(fine) - half).max() < 0.3 * UM
    assert np.abs(model.predict(fine, 1) - (curve(fine) + half)).max() < 0.5 * UM


def test_one_directional_groups_that_differ_are_refused():
    rng = np.random.default_rng(1)
    nominal = np.linspace(0.0, 0.07, 8)
    up = synthetic_calibration("z", nominal, lambda v: 0 * v, repeats=2, measurement_noise=0.4 * UM,
                               reference_noise=0.1 * UM, directions=(1,), rng=rng)
    down = synthetic_calibration("z", nominal, lambda v: 0 * v, repeats=2, measurement_noise=0.4 * UM,
                                 reference_noise=0.1 * UM, directions=(-1,), rng=rng)
    data = CalibrationData("z", np.r_[up.measured, down.measured], np.r_[up.reference, down.reference],
                           np.r_[np.zeros(up.measured.size), np.ones(down.measured.size)],
                           np.r_[up.point, down.point], np.r_[up.direction, down.direction])
    with pytest.raises(ValueError, match="cannot be told apart"):
        SmoothingSplineCompensator().fit(data)


def test_the_record_reports_directions_it_did_not_cover():
    one_way = hard_campaign(5, "a", hysteresis=True, bidirectional=False).calibration
    assert one_way.directions == (1,)
    record = calibrate(one_way, {"csf": SmoothingSplineCompensator()}, method="csf", evaluation=False)
    assert record.approach_directions("a") == (1,) and not record.bidirectional
    value = float(np.mean(one_way.measured))
    assert not np.any(record.correct("a", value, direction=1).direction_not_covered)
    assert not np.any(record.correct("a", value).direction_not_covered)  # unknown direction: nothing asked
    result = record.correct("a", np.array([value, value]), direction=np.array([1, -1]))
    np.testing.assert_array_equal(result.direction_not_covered, [False, True])
    assert not result.ok and "approached from +1 only" in result.messages()[0]
    # a calibration that recorded no direction cannot vouch for any
    unrecorded = CalibrationData("a", one_way.measured, one_way.reference, one_way.group, one_way.point)
    record = calibrate(unrecorded, {"csf": SmoothingSplineCompensator()}, method="csf", evaluation=False)
    assert record.approach_directions("a") == ()
    flagged = record.correct("a", value, direction=1)
    assert bool(flagged.direction_not_covered) and "recorded no approach direction" in flagged.messages()[0]


def test_a_bidirectional_record_says_so_and_corrects_each_direction(campaign):
    record = calibrate(campaign.calibration, {"csf": SmoothingSplineCompensator()}, method="csf", evaluation=False)
    assert record.bidirectional and record.approach_directions("x") == (-1, 1)
    held = campaign.held_out[0]
    corrected = record.correct("x", held.measured, held.direction)
    assert corrected.ok
    offsets = np.array([record.models["x"].group_offset(g) for g in held.group])
    residual = corrected.corrected - held.reference + offsets  # = error − prediction in the group's frame
    oracle = held.error - held.oracle_error
    assert rms(residual) < 1.3 * rms(oracle)
