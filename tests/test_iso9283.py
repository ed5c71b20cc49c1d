"""ISO 9283 characteristics: hand-computed cases, the angle branch rule, the statistical oracle,
confidence-interval coverage, the test cube, and bad inputs."""

import numpy as np
import pytest

from instrument.iso9283 import (
    ISO9283Error,
    distance_characteristics,
    iso_cube_points,
    multidirectional_variation,
    pose_accuracy,
    pose_drift,
    pose_repeatability,
    wrap_angle,
)

MAXWELL_RP = 2 * np.sqrt(2 / np.pi) + 3 * np.sqrt(3 - 8 / np.pi)  # population l̄ + 3·S_l per σ: 3.6165


def poses_from(positions, angles=None):
    positions = np.asarray(positions, dtype=float)
    angles = np.zeros_like(positions) if angles is None else np.asarray(angles, dtype=float)
    return np.column_stack([positions, angles])


def test_repeatability_hand_computed():
    d = 1e-5
    poses = poses_from(
        [[0, 0, 0], [0, 0, 0], [0, 0, 0], [4 * d, 0, 0]], [[0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0], [0.2, 0, 0]]
    )
    rp = pose_repeatability(poses)
    # barycentre x = d, so l = (d, d, d, 3d): l̄ = 1.5d, S_l = d, RP_l = 4.5d
    np.testing.assert_allclose(rp.barycentre, [d, 0, 0, 0.2, 0, 0], atol=1e-15)
    assert rp.l_mean == pytest.approx(1.5 * d)
    assert rp.s_l == pytest.approx(d)
    assert rp.rp_l == pytest.approx(4.5 * d)
    assert rp.s_a == pytest.approx(np.sqrt(0.02 / 3))
    assert rp.rp_a == pytest.approx(3 * np.sqrt(0.02 / 3))
    assert rp.rp_b == 0.0 and rp.rp_c == 0.0 and rp.n == 4
    assert rp.rp_l_ci is None


def test_accuracy_hand_computed():
    poses = poses_from([[0.1, 0.2, 0.3], [0.1, 0.2, 0.302]], [[0.01, -0.02, 0.5], [0.03, -0.02, 0.7]])
    ap = pose_accuracy(poses, [0.1, 0.2, 0.298, 0.0, 0.0, 0.5])
    assert ap.ap_p == pytest.approx(0.003)
    assert (ap.ap_x, ap.ap_y, ap.ap_z) == pytest.approx((0.0, 0.0, 0.003), abs=1e-15)
    assert (ap.ap_a, ap.ap_b, ap.ap_c) == pytest.approx((0.02, -0.02, 0.1))


def test_angles_near_pi_stay_on_one_branch():
    c = np.array([np.pi - 0.01, -np.pi + 0.01, np.pi - 0.02, -np.pi + 0.02])
    poses = poses_from(np.zeros((4, 3)), np.column_stack([np.zeros(4), np.zeros(4), c]))
    rp = pose_repeatability(poses)
    assert rp.barycentre[5] == pytest.approx(np.pi)  # not 0, and wrapped into (−π, π]
    assert rp.s_c == pytest.approx(np.sqrt((2 * 0.01**2 + 2 * 0.02**2) / 3))
    assert pose_accuracy(poses, [0, 0, 0, 0, 0, -np.pi]).ap_c == pytest.approx(0.0, abs=1e-12)
    assert pose_accuracy(poses, [0, 0, 0, 0, 0, np.pi - 0.05]).ap_c == pytest.approx(0.05)
    assert pose_accuracy(poses, [0, 0, 0, 0, 0, -np.pi + 0.05]).ap_c == pytest.approx(-0.05)
    assert wrap_angle(-np.pi) == np.pi and wrap_angle(3 * np.pi) == np.pi


def test_distance_accuracy_and_repeatability_hand_computed():
    n = 4
    second = poses_from(np.zeros((n, 3)), np.zeros((n, 3)))
    first = poses_from(
        [[0.100, 0, 0], [0.101, 0, 0], [0.099, 0, 0], [0.100, 0.0, 0]],
        [[0.0, 0, 3.1], [0.0, 0, 3.1], [0, 0, 3.1], [0, 0, 3.1]],
    )
    second[:, 5] = -3.1
    result = distance_characteristics(first, second, [0.1005, 0, 0, 0, 0, 3.1], [0, 0, 0, 0, 0, -3.1])
    assert result.commanded_distance == pytest.approx(0.1005)
    assert result.mean_distance == pytest.approx(0.1)
    assert result.ad_p == pytest.approx(-0.0005)
    assert result.ad_x == pytest.approx(-0.0005)
    assert result.rd_p == pytest.approx(3 * np.std([0.1, 0.101, 0.099, 0.1], ddof=1))
    assert result.rd_x == pytest.approx(result.rd_p)
    # c differences 3.1 − (−3.1) = 6.2 wrap to 6.2 − 2π both measured and commanded: AD_c = 0
    assert result.ad_c == pytest.approx(0.0, abs=1e-12) and result.rd_c == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ISO9283Error, match="pair up cycle by cycle"):
        distance_characteristics(first, second[:3], np.zeros(6), np.zeros(6))


def test_multidirectional_variation_hand_computed():
    base = np.zeros((5, 6))
    a, b, c = base.copy(), base.copy(), base.copy()
    b[:, 0] = 3e-5
    c[:, 1] = 4e-5
    a[:, 5], b[:, 5], c[:, 5] = np.pi - 0.001, -np.pi + 0.002, np.pi
    variation = multidirectional_variation([a, b, c])
    assert variation.vap_p == pytest.approx(5e-5)  # between b and c
    assert variation.vap_c == pytest.approx(0.003)  # across the ±π seam, not 2π
    assert variation.vap_a == 0.0 and variation.directions == 3
    with pytest.raises(ISO9283Error, match="at least 2 approach directions"):
        multidirectional_variation([a])
    with pytest.raises(ISO9283Error, match="one \\(n, 6\\) array per approach direction"):
        multidirectional_variation(a)


def test_drift():
    rng = np.random.default_rng(4)
    first = poses_from(rng.normal(0, 1e-5, (30, 3)), rng.normal(0, 1e-5, (30, 3)))
    last = first * 2.0
    last[:, 0] += 2e-4
    drift = pose_drift(first, last, np.zeros(6))
    ap1, rp1 = drift.first
    ap2, rp2 = drift.last
    assert drift.drp_l == pytest.approx(rp1.rp_l)  # scatter doubled
    assert drift.drp_a == pytest.approx(rp1.rp_a)
    assert drift.dap_p == pytest.approx(abs(ap2.ap_p - ap1.ap_p))
    assert drift.dap_p > 1.5e-4


def test_statistical_oracle_rp_l_is_3_54_sigma_for_n_30():
    sigma = 2e-5
    rng = np.random.default_rng(2023)
    values = [pose_repeatability(poses_from(rng.normal(0, sigma, (30, 3)))).rp_l / sigma for _ in range(2000)]
    # One RP_l/σ has a spread of ≈ 0.33; over 2000 trials the mean is known to ± 0.0074.
    assert np.mean(values) == pytest.approx(3.54, abs=0.03)


def test_confidence_intervals_cover_the_truth():
    sigma, n, trials = 1e-5, 30, 200
    rng = np.random.default_rng(99)
    hits = {"rp_l": 0, "rp_a": 0, "ap_p": 0, "ap_b": 0}
    commanded = np.array([3e-5, 0, 0, 0, 1e-5, 0])
    for trial in range(trials):
        poses = poses_from(rng.normal(0, sigma, (n, 3)), rng.normal(0, sigma, (n, 3)))
        rp = pose_repeatability(poses, confidence=0.95, bootstrap_samples=1000, seed=trial)
        ap = pose_accuracy(poses, commanded, confidence=0.95, bootstrap_samples=1000, seed=trial)
        hits["rp_l"] += rp.rp_l_ci[0] <= MAXWELL_RP * sigma <= rp.rp_l_ci[1]
        hits["rp_a"] += rp.rp_a_ci[0] <= 3 * sigma <= rp.rp_a_ci[1]
        hits["ap_p"] += ap.ap_p_ci[0] <= 3e-5 <= ap.ap_p_ci[1]
        hits["ap_b"] += ap.ap_b_ci[0] <= -1e-5 <= ap.ap_b_ci[1]
    coverage = {key: value / trials for key, value in hits.items()}
    # Nominal 0.95; binomial s.e. over 200 trials ≈ 0.015. The bootstrap-t for RP_l runs ≈ 0.92.
    assert coverage["rp_a"] >= 0.9 and coverage["ap_b"] >= 0.9
    assert coverage["rp_l"] >= 0.86 and coverage["ap_p"] >= 0.86
    assert max(coverage.values()) <= 0.995


def test_rp_l_interval_has_no_runaway_widths():
    """A resample full of duplicates must not stretch the interval to several times RP_l."""
    sigma, n, trials = 1e-5, 30, 200
    rng = np.random.default_rng(7)
    widths = []
    for trial in range(trials):
        rp = pose_repeatability(poses_from(rng.normal(0, sigma, (n, 3))), confidence=0.95, bootstrap_samples=1000,
                                seed=trial)
        widths.append((rp.rp_l_ci[1] - rp.rp_l_ci[0]) / (MAXWELL_RP * sigma))
    # The delta-method standard error of RP_l is ≈ 0.08·RP_l at n = 30, so a 95 % interval is
    # ≈ 0.3·RP_l wide; unfloored studentisation gave a 95th percentile of 0.83 and maxima of 1.7.
    assert np.median(widths) < 0.45
    assert np.quantile(widths, 0.95) < 0.7


def test_confidence_intervals_are_reproducible_and_bracket_the_estimate():
    rng = np.random.default_rng(1)
    poses = poses_from(rng.normal(0, 1e-5, (30, 3)), rng.normal(0, 1e-5, (30, 3)))
    first = pose_repeatability(poses, confidence=0.9, seed=5)
    assert first.rp_l_ci == pose_repeatability(poses, confidence=0.9, seed=5).rp_l_ci
    assert first.rp_l_ci != pose_repeatability(poses, confidence=0.9, seed=6).rp_l_ci
    for low, value, high in [
        (first.rp_l_ci[0], first.rp_l, first.rp_l_ci[1]),
        (first.rp_b_ci[0], first.rp_b, first.rp_b_ci[1]),
    ]:
        assert low < value < high
    assert first.confidence == 0.9


def test_iso_cube():
    center, edge = np.array([0.5, -0.1, 0.4]), 0.2
    cube = iso_cube_points(center, edge)
    np.testing.assert_allclose(cube.points["P1"], center)
    diagonal = edge * np.sqrt(3)
    for point, corner in (("P2", "C1"), ("P3", "C2"), ("P4", "C7"), ("P5", "C8")):
        assert np.linalg.norm(cube.points[point] - cube.corners[corner]) == pytest.approx(0.1 * diagonal)
        local = cube.points[point] - center
        assert local[1] == pytest.approx(local[2])  # all in the plane C1-C2-C7-C8 (y = z locally)
    assert cube.order == ("P1", "P5", "P4", "P3", "P2")
    assert cube.cycle(2) == ["P1", "P5", "P4", "P3", "P2"] * 2
    np.testing.assert_allclose(cube.positions_in_order()[1], cube.points["P5"])
    turned = iso_cube_points(center, edge, rotation=np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]))
    for name in cube.points:
        assert np.linalg.norm(turned.points[name] - center) == pytest.approx(np.linalg.norm(cube.points[name] - center))
    with pytest.raises(ISO9283Error, match="edge"):
        iso_cube_points(center, -0.1)
    with pytest.raises(ISO9283Error, match="center"):
        iso_cube_points([0, 0], 0.1)
    with pytest.raises(ISO9283Error, match="rotation"):
        iso_cube_points(center, 0.1, rotation=np.diag([1, 1, -1.0]))


@pytest.mark.parametrize(
    "poses, message",
    [
        (np.zeros((1, 6)), "at least 2 attained poses"),
        (np.zeros((5, 5)), r"\(n, 6\) array"),
        (np.zeros(6), r"\(n, 6\) array"),
        (np.where(np.eye(6, dtype=bool)[:5], np.nan, 0.0), "non-finite value at pose 0, column 'x'"),
        ([["a"] * 6] * 3, "of numbers"),
        (np.column_stack([np.zeros((4, 5)), [0, np.pi / 2, np.pi, -np.pi / 2]]), "spread around the whole circle"),
    ],
)
def test_bad_inputs(poses, message):
    with pytest.raises(ISO9283Error, match=message):
        pose_repeatability(poses)


def test_bad_options():
    poses = np.zeros((10, 6))
    with pytest.raises(ISO9283Error, match="confidence"):
        pose_repeatability(poses, confidence=95)
    with pytest.raises(ISO9283Error, match="at least 3"):
        pose_repeatability(np.zeros((2, 6)), confidence=0.95)
    with pytest.raises(ISO9283Error, match="commanded"):
        pose_accuracy(poses, [0, 0, 0])
    with pytest.raises(ISO9283Error, match="commanded"):
        pose_accuracy(poses, [0, 0, 0, 0, 0, np.inf])
    with pytest.raises(ISO9283Error, match="bootstrap_samples"):
        pose_accuracy(np.random.default_rng(0).normal(size=(10, 6)), np.zeros(6), confidence=0.9, bootstrap_samples=10)


def test_rp_l_interval_never_collapses_for_small_samples():
    """n = 5: the delta-method variance can come out negative; the interval must still have a width."""
    rng = np.random.default_rng(3)
    widths = []
    for _ in range(300):
        poses = np.zeros((5, 6))
        poses[:, :3] = rng.normal(0.0, 10e-6, (5, 3))
        low, high = pose_repeatability(poses, confidence=0.95).rp_l_ci
        widths.append(high - low)
    assert min(widths) > 0.0
