"""solve_pose and small_motion_pose against known truth: exact round trips, noise, every bad input."""

import dataclasses

import numpy as np
import pytest

from instrument.pose import (
    CrossOffScreenError,
    Geometry,
    InconsistentCrossesError,
    MissingScreenError,
    Pose,
    PoseError,
    StripeMatchError,
    observe_crosses,
    predict_measurements,
    small_motion_pose,
    solve_pose,
)
from instrument.vision import StripeLine
from tests.test_pose_station import AWKWARD_CAMERAS, METRES_PER_PIXEL, station_dict

NOMINAL = Geometry.from_dict(station_dict())
AWKWARD = Geometry.from_dict(station_dict(AWKWARD_CAMERAS))
FANS = ("xy", "xz", "yz", "yx", "zx", "zy")


def random_pose(rng, translation=0.05, rotation_deg=2.0):
    return Pose.from_euler(
        rng.uniform(-translation, translation, 3), np.radians(rng.uniform(-rotation_deg, rotation_deg, 3))
    )


def errors(estimate, truth):
    return float(np.abs(estimate.translation - truth.translation).max()), truth.rotation_angle_to(
        estimate.pose if hasattr(estimate, "pose") else estimate
    )


@pytest.mark.parametrize("geometry", [NOMINAL, AWKWARD], ids=["nominal cameras", "mirrored+turned cameras"])
def test_round_trip_recovers_random_poses_exactly(geometry):
    rng = np.random.default_rng(11)
    for _ in range(25):
        truth = random_pose(rng)
        estimate = solve_pose(predict_measurements(truth, geometry), geometry)
        position_error, angle_error = errors(estimate, truth)
        assert position_error < 1e-9 and angle_error < 1e-9
        np.testing.assert_allclose(estimate.euler, truth.euler, atol=1e-9)
        assert estimate.residual_rms < 1e-9
        assert set(estimate.stripe_residuals) == set(FANS)
        assert estimate.residuals.shape == (12,)


def test_every_camera_turn_and_mirror_gives_the_same_pose():
    """Stripe ↔ fan matching is decided on the screen: camera turns from 0 to 330°, mirrored or not."""
    truth = Pose.from_euler([0.011, -0.023, 0.031], np.radians([1.2, -0.7, 1.9]))
    for turn in np.radians(np.arange(0, 360, 30)):
        for mirrored in (False, True):
            cameras = {name: (turn + offset, mirrored, (1e-5, 0.0)) for name, offset in zip("xyz", (0.0, 0.4, -0.9))}
            geometry = Geometry.from_dict(station_dict(cameras))
            estimate = solve_pose(predict_measurements(truth, geometry), geometry)
            assert max(errors(estimate, truth)) < 1e-9


def test_accepts_screen_crosses_and_an_initial_guess():
    truth = random_pose(np.random.default_rng(2))
    crosses = observe_crosses(predict_measurements(truth, AWKWARD), AWKWARD)
    assert max(errors(solve_pose(crosses, AWKWARD), truth)) < 1e-9
    assert max(errors(solve_pose(crosses, AWKWARD, initial=Pose.identity()), truth)) < 1e-9


def test_distortion_is_corrected():
    distortion = {name: {"k1": 1.5e-9, "k2": 0.0, "center_px": [505.0, 525.0]} for name in "xyz"}
    distorted = Geometry.from_dict(station_dict(AWKWARD_CAMERAS, distortion=distortion))
    rng = np.random.default_rng(5)
    for _ in range(5):
        truth = random_pose(rng)
        measurements = predict_measurements(truth, distorted)  # curved stripes, fitted with straight lines
        corrected = solve_pose(measurements, distorted)
        ignored = solve_pose(measurements, AWKWARD, max_residual_rms=None)
        # Straight lines fitted to slightly curved stripes: small residual error, far below ignoring it.
        assert errors(corrected, truth)[0] < 2e-6
        assert errors(ignored, truth)[0] > 5 * errors(corrected, truth)[0]


def test_pixel_noise_error_is_linear_in_sigma():
    truth = Pose.from_euler([0.02, 0.01, -0.015], np.radians([0.5, -1.0, 1.5]))
    results = {}
    for sigma in (0.01, 0.02, 0.04):
        # Same seed: the same noise pattern, scaled — the error must scale with it.
        estimate = solve_pose(
            predict_measurements(truth, AWKWARD, noise_px=sigma, rng=np.random.default_rng(9)), AWKWARD
        )
        results[sigma] = np.r_[estimate.translation - truth.translation, estimate.euler - truth.euler]
    np.testing.assert_allclose(results[0.02], 2 * results[0.01], rtol=0.02, atol=1e-12)
    np.testing.assert_allclose(results[0.04], 4 * results[0.01], rtol=0.02, atol=1e-12)


def test_pixel_noise_error_has_the_expected_size():
    """Per-section noise σ averages down along ~900-section stripes: the pose error is a small
    fraction of one section's σ·(0.156 mm/px), and its spread scales with σ."""
    spreads = {}
    for sigma in (0.02, 0.08):
        rng = np.random.default_rng(21)
        position_errors, residuals = [], []
        for _ in range(30):
            truth = random_pose(rng)
            estimate = solve_pose(predict_measurements(truth, NOMINAL, noise_px=sigma, rng=rng), NOMINAL)
            position_errors.append(estimate.translation - truth.translation)
            residuals.append(estimate.residual_rms)
        spreads[sigma] = float(np.std(position_errors))
        assert spreads[sigma] < 0.2 * sigma * METRES_PER_PIXEL
        assert np.mean(residuals) < 0.2 * sigma * METRES_PER_PIXEL
    assert spreads[0.08] / spreads[0.02] == pytest.approx(4.0, rel=0.35)


def test_missing_screen():
    measurements = predict_measurements(Pose.identity(), NOMINAL)
    del measurements["y"]
    with pytest.raises(MissingScreenError, match="screen\\(s\\) y"):
        solve_pose(measurements, NOMINAL)
    with pytest.raises(MissingScreenError, match="x, z"):
        solve_pose({"y": predict_measurements(Pose.identity(), NOMINAL)["y"]}, NOMINAL)
    with pytest.raises(MissingScreenError):
        solve_pose({**predict_measurements(Pose.identity(), NOMINAL), "z": None}, NOMINAL)
    with pytest.raises(PoseError, match="expected a mapping"):
        solve_pose([1, 2, 3], NOMINAL)


def test_cross_off_the_screen():
    measurements = predict_measurements(Pose.identity(), NOMINAL)
    measurements["x"] = dataclasses.replace(measurements["x"], center=np.array([1100.0, 300.0]))
    with pytest.raises(CrossOffScreenError, match="screen 'x'.*off the 1024×1040 px image"):
        solve_pose(measurements, NOMINAL)


def test_non_finite_measurement():
    measurements = predict_measurements(Pose.identity(), NOMINAL)
    broken = dataclasses.replace(measurements["z"].vertical, point=np.array([np.nan, 3.0]))
    measurements["z"] = dataclasses.replace(measurements["z"], vertical=broken)
    with pytest.raises(PoseError, match="screen 'z': vertical stripe has a non-finite"):
        solve_pose(measurements, NOMINAL)
    measurements = predict_measurements(Pose.identity(), NOMINAL)
    measurements["y"] = dataclasses.replace(measurements["y"], center=np.array([np.nan, np.nan]))
    with pytest.raises(PoseError, match="screen 'y': cross centre is not a finite"):
        solve_pose(measurements, NOMINAL)


def _turned(stripe: StripeLine, angle: float) -> StripeLine:
    c, s = np.cos(angle), np.sin(angle)
    return dataclasses.replace(stripe, direction=np.array([[c, -s], [s, c]]) @ stripe.direction)


def test_stripes_that_cannot_be_matched_or_are_parallel():
    measurements = predict_measurements(Pose.identity(), NOMINAL)
    cross = measurements["z"]
    measurements["z"] = dataclasses.replace(
        cross, horizontal=_turned(cross.horizontal, np.radians(45)), vertical=_turned(cross.vertical, np.radians(45))
    )
    with pytest.raises(StripeMatchError, match="screen 'z'"):
        solve_pose(measurements, NOMINAL)
    measurements["z"] = dataclasses.replace(
        cross, vertical=dataclasses.replace(cross.vertical, direction=cross.horizontal.direction)
    )
    with pytest.raises(CrossOffScreenError, match="nearly parallel"):
        solve_pose(measurements, NOMINAL)


def test_inconsistent_crosses_are_refused_with_the_residual():
    first = Pose.from_euler([0.01, 0.0, 0.0], np.zeros(3))
    second = Pose.from_euler([0.01, 0.0, 0.002], np.zeros(3))  # z differs by 2 mm
    measurements = predict_measurements(first, AWKWARD)
    measurements["y"] = predict_measurements(second, AWKWARD)["y"]
    with pytest.raises(InconsistentCrossesError, match="do not come from one rigid pose") as caught:
        solve_pose(measurements, AWKWARD)
    assert caught.value.residual_rms > caught.value.threshold
    # The limit is configurable; switched off, the best fit comes back with its residual.
    estimate = solve_pose(measurements, AWKWARD, max_residual_rms=None)
    assert estimate.residual_rms > 1e-4
    assert max(estimate.stripe_residuals.values()) > 1e-4
    with pytest.raises(InconsistentCrossesError):
        solve_pose(
            predict_measurements(first, AWKWARD, noise_px=0.05, rng=np.random.default_rng(1)),
            AWKWARD,
            max_residual_rms=1e-9,
        )


def test_closed_form_is_exact_for_pure_translation_and_departs_with_rotation():
    rng = np.random.default_rng(4)
    for _ in range(5):
        truth = Pose(rng.uniform(-0.05, 0.05, 3), np.eye(3))
        closed = small_motion_pose(predict_measurements(truth, AWKWARD), AWKWARD)
        assert max(errors(closed, truth)) < 1e-9

    def worst(translation, rotation_deg, lever):
        worst_error = np.zeros(2)
        for sign in (-1.0, 1.0):
            truth = Pose.from_euler([translation, -translation, translation], sign * np.radians([rotation_deg] * 3))
            closed = small_motion_pose(predict_measurements(truth, NOMINAL), NOMINAL, lever=lever)
            worst_error = np.maximum(worst_error, errors(closed, truth))
        return worst_error

    # Pure rotation: a second-order model error; doubling the angle multiplies it by about 4.
    small, large = worst(0.0, 0.5, "exact"), worst(0.0, 1.0, "exact")
    assert 3.0 < large[0] / small[0] < 5.0 and 3.0 < large[1] / small[1] < 5.0
    # The paper's lever (beam-axis translation dropped) adds an error ~ |t|·angle.
    assert worst(0.05, 0.5, "paper")[0] > 10 * worst(0.05, 0.5, "exact")[0]
    assert worst(0.05, 0.5, "paper")[0] > 1e-4  # > 0.1 mm: why the exact solver is needed
    with pytest.raises(ValueError, match="lever"):
        small_motion_pose(predict_measurements(Pose.identity(), NOMINAL), NOMINAL, lever="magic")
