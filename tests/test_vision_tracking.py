"""The tracking path of ``locate_cross`` (a prior from the previous frame) against known truth.

Images come from tests/synthetic_cross.py with noise the locator is not told about. A tracked
result must be as accurate as the full search on the same image (it runs the same fine stage from
a different coarse line), must follow a cross that moved within the search band, and must fall
back to the full search — and say why — when the prior is lost.
"""

import numpy as np
import pytest

from instrument.vision import CoarseLine, CrossNotFound, VisionWorkspace, locate_cross, locate_crosses
from instrument.vision._bands import BAND_HALF_WIDTH, _kept_sections
from tests.synthetic_cross import render_cross

SHAPE = (480, 640)  # rows, cols


def _frame(center, angle=0.1, seed=0, **kwargs):
    kwargs.setdefault("shape", SHAPE)
    return render_cross(center=center, angle=angle, perpendicularity=0.01, seed=seed, **kwargs)


def test_tracked_result_matches_the_full_search_on_the_same_image():
    prior = locate_cross(_frame((300.0, 250.0), seed=1)[0])
    img, truth = _frame((306.4, 244.7), angle=0.104, seed=2)
    tracked = locate_cross(img, prior=prior)
    full = locate_cross(img)
    assert tracked.search == "tracked" and tracked.lost_reason is None
    assert full.search == "full"
    # the same fine stage from two coarse lines a fraction of a pixel apart: the same answer
    assert np.hypot(*(tracked.center - full.center)) < 2e-3
    assert abs(tracked.angle - full.angle) < 2e-5
    assert np.hypot(*(tracked.center - truth.center)) < 0.02


def test_tracking_is_as_accurate_as_the_full_search_on_hidden_noise_images():
    """RMS centre and angle error over 12 noisy frames: tracked ≤ 1.1 × full search."""
    rng = np.random.default_rng(5)
    errors = {"full": [], "tracked": []}
    for i in range(12):
        center = np.array([rng.uniform(200, 440), rng.uniform(150, 330)])
        angle = rng.uniform(-0.4, 0.4)
        prior = locate_cross(_frame(center, angle, seed=100 + i)[0])
        motion = rng.uniform(-8.0, 8.0, 2)  # px between the two frames
        img, truth = _frame(center + motion, angle + rng.uniform(-0.01, 0.01), seed=200 + i)
        for name, result in (("full", locate_cross(img)), ("tracked", locate_cross(img, prior=prior))):
            errors[name].append([*(result.center - truth.center), result.angle - truth.angle])
        assert result.search == "tracked"
    full, tracked = np.array(errors["full"]), np.array(errors["tracked"])
    centre_rms = [np.sqrt(np.mean(np.sum(e[:, :2] ** 2, axis=1))) for e in (full, tracked)]
    angle_rms = [np.sqrt(np.mean(e[:, 2] ** 2)) for e in (full, tracked)]
    assert centre_rms[1] <= 1.1 * centre_rms[0], centre_rms
    assert angle_rms[1] <= 1.1 * angle_rms[0], angle_rms
    assert centre_rms[1] < 0.01  # px: and both are sub-pixel-accurate in absolute terms


def test_follows_a_cross_that_moved_within_the_search_band():
    prior = locate_cross(_frame((320.0, 240.0), angle=0.05, seed=3)[0])
    img, truth = _frame((337.0, 226.0), angle=0.07, seed=4)  # 17 px and 14 px, 1.1°
    m = locate_cross(img, prior=prior)
    assert m.search == "tracked"
    assert np.hypot(*(m.center - truth.center)) < 0.02
    assert abs(m.angle - truth.angle) < 2e-4


def test_a_cross_beyond_the_search_band_falls_back_to_the_full_search():
    prior = locate_cross(_frame((320.0, 240.0), seed=5)[0])
    img, truth = _frame((380.0, 200.0), seed=6)  # 60 px away: outside ±24 px
    m = locate_cross(img, prior=prior)
    assert m.search == "fallback"
    assert "not found within ±24 px" in m.lost_reason
    assert np.hypot(*(m.center - truth.center)) < 0.02
    # a wider search band follows it
    assert locate_cross(img, prior=prior, search_px=80).search == "tracked"


def test_a_shortened_stripe_falls_back_and_says_so():
    prior = locate_cross(_frame((320.0, 240.0), seed=7)[0])
    img, truth = _frame((320.0, 240.0), seed=8, h_extent=(200.0, 420.0))  # horizontal stripe cut short
    m = locate_cross(img, prior=prior)
    assert m.search == "fallback"
    assert m.lost_reason.startswith("near-horizontal stripe")
    assert np.hypot(*(m.center - truth.center)) < 0.05


def test_a_vanished_stripe_is_an_error_not_a_guess():
    prior = locate_cross(_frame((320.0, 240.0), seed=9)[0])
    img, _ = _frame((320.0, 240.0), seed=10, vertical=False)
    with pytest.raises(CrossNotFound, match="only one stripe"):
        locate_cross(img, prior=prior)


def test_tracks_near_the_frame_edge_and_in_12_bit():
    twelve_bit = dict(dtype=np.uint16, saturation=4095, amplitude=3200.0, background=150.0, noise=32.0)
    prior = locate_cross(_frame((8.0, 470.0), seed=11, **twelve_bit)[0], saturation=4095)
    img, truth = _frame((12.5, 466.0), seed=12, **twelve_bit)
    m = locate_cross(img, saturation=4095, prior=prior)
    assert m.search == "tracked"
    assert np.hypot(*(m.center - truth.center)) < 0.05


def test_saturated_stripes_are_tracked_as_accurately():
    prior = locate_cross(_frame((300.0, 250.0), seed=13, amplitude=700.0)[0])
    img, truth = _frame((303.0, 252.0), seed=14, amplitude=700.0)
    tracked, full = locate_cross(img, prior=prior), locate_cross(img)
    assert tracked.search == "tracked"
    assert np.hypot(*(tracked.center - full.center)) < 2e-3
    assert np.hypot(*(tracked.center - truth.center)) < 0.03


def test_bad_prior_and_search_band():
    img, _ = _frame((320.0, 240.0), seed=15)
    with pytest.raises(TypeError, match="prior must be the CrossMeasurement"):
        locate_cross(img, prior=(320.0, 240.0))
    prior = locate_cross(img)
    for bad in (2, 1000, 10.5):
        with pytest.raises(ValueError, match="search_px"):
            locate_cross(img, prior=prior, search_px=bad)


def test_several_frames_at_once_give_what_each_frame_gives_alone():
    """locate_crosses: tracked, full-search, fallback and failing frames in one call."""
    twelve_bit = dict(dtype=np.uint16, saturation=4095, amplitude=3200.0, background=150.0, noise=32.0)
    priors = {
        "tracked": locate_cross(_frame((300.0, 250.0), seed=20)[0]),
        "lost": locate_cross(_frame((320.0, 240.0), seed=21)[0]),
        "12-bit": locate_cross(_frame((200.0, 300.0), seed=22, **twelve_bit)[0], saturation=4095),
    }
    images = {
        "tracked": _frame((304.0, 247.0), seed=23)[0],
        "lost": _frame((400.0, 190.0), seed=24)[0],
        "12-bit": _frame((203.0, 301.0), seed=25, **twelve_bit)[0],
        "full": _frame((250.0, 260.0), seed=26)[0],
        "none": _frame((250.0, 260.0), seed=27, horizontal=False, vertical=False)[0],
    }
    saturation = {"12-bit": 4095}
    together = locate_crosses(images, saturation, priors)
    assert list(together) == list(images)
    for name, img in images.items():
        try:
            alone = locate_cross(img, saturation.get(name), priors.get(name))
        except CrossNotFound as exc:
            assert isinstance(together[name], CrossNotFound) and str(together[name]) == str(exc)
            continue
        got = together[name]
        assert got.search == alone.search and got.lost_reason == alone.lost_reason
        np.testing.assert_allclose(got.center, alone.center, atol=1e-9)
        assert got.angle == pytest.approx(alone.angle, abs=1e-12)
    assert [together[n].search for n in ("tracked", "lost", "12-bit", "full")] == [
        "tracked", "fallback", "tracked", "full"]


def test_a_cross_within_the_band_of_its_prior_lines_is_measured_there_as_precisely():
    """Small motion (≤ 2 px: the band on the prior's lines is kept) and larger motion (the band is
    laid again where the stripes are): both as accurate as the full search, against the truth."""
    for motion, seed in (((0.8, -1.1), 30), ((4.5, 3.0), 32)):
        prior = locate_cross(_frame((300.0, 250.0), seed=seed)[0])
        img, truth = _frame((300.0 + motion[0], 250.0 + motion[1]), angle=0.101, seed=seed + 1)
        tracked, full = locate_cross(img, prior=prior), locate_cross(img)
        assert tracked.search == "tracked"
        assert np.hypot(*(tracked.center - truth.center)) < 0.02
        # a band laid on the prior's line (≤ 2 px off) or on the stripe: sub-millipixel agreement
        assert np.hypot(*(tracked.center - full.center)) < 2e-3
        assert abs(tracked.angle - full.angle) < 2e-5


def test_a_workspace_changes_nothing_but_the_memory_reused():
    """Results with a reused VisionWorkspace equal those with fresh memory, and no result refers
    to the workspace (later calls through it leave earlier results as they were)."""
    frames = [_frame((300.0 + 2 * k, 250.0 - k), angle=0.1 + 0.002 * k, seed=40 + k)[0] for k in range(4)]
    workspace = VisionWorkspace()
    kept, fresh, prior_kept, prior_fresh = [], [], None, None
    for img in frames:
        prior_kept = locate_cross(img, prior=prior_kept, workspace=workspace)
        prior_fresh = locate_cross(img, prior=prior_fresh)
        kept.append((prior_kept, prior_kept.center.copy(), prior_kept.horizontal.point.copy()))
        fresh.append(prior_fresh)
    for (m, center, point), f in zip(kept, fresh):
        np.testing.assert_array_equal(m.center, f.center)
        assert m.angle == f.angle and m.search == f.search
        np.testing.assert_array_equal(m.center, center)  # untouched by the later calls
        np.testing.assert_array_equal(m.horizontal.point, point)
    assert workspace.nbytes > 0


def test_band_sections_found_from_the_crossing_points_equal_the_elementwise_test():
    """The kept sections of a band (outside the crossing zone, line in the frame) computed from
    the analytic crossing points equal a test of every section, for random and degenerate lines."""
    rng = np.random.default_rng(3)
    for _ in range(3000):
        n, across = (int(v) for v in rng.integers(16, 2500, 2))
        vertical = bool(rng.integers(2))
        slope = float(rng.choice([rng.uniform(-1, 1), 0.0, 0.5, -0.25, 1e-300]))
        other_slope = float(rng.choice([rng.uniform(-1, 1), 0.0, 0.5]))
        intercept = float(rng.choice([rng.uniform(-100, across + 100), rng.integers(-50, across + 50) + 0.5]))
        line = CoarseLine(vertical, intercept, slope, 0)
        other = CoarseLine(not vertical, float(rng.uniform(-100, n + 100)), other_slope, 0)
        s = np.arange(n)
        position = line.at(s)
        reach = BAND_HALF_WIDTH * (1.0 + abs(other_slope)) + BAND_HALF_WIDTH
        keep = (np.abs(s - other.at(position)) > reach) & (position > -BAND_HALF_WIDTH)
        keep &= position < across - 1 + BAND_HALF_WIDTH
        np.testing.assert_array_equal(_kept_sections(n, across, line, other), s[keep])
