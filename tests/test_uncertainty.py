"""instrument.uncertainty: the budget's parts, the Monte Carlo propagation against analytic
results, the physics of each correlation type, the export shape, and bad input."""

import json
import math

import numpy as np
import pytest

from instrument import ARCSEC
from instrument.iso9283 import pose_accuracy, pose_repeatability
from instrument.pose import Pose
from instrument.uncertainty import (
    BudgetTerm,
    Correlation,
    IsoRun,
    UncertaintyBudget,
    UncertaintyError,
    calibration_residual_uncertainty,
    compensation_term,
    environment_term,
    frame_noise_from_calibration,
    frame_noise_from_frames,
    frame_noise_from_residuals,
    interferometer_terms,
    iso_uncertainty,
    rotary_table_term,
    transform_term,
)
from instrument.uncertainty._rotation import compose, decompose, euler_to_matrix, matrix_to_euler

UM = 1e-6
POINTS = {"P1": [0.035, 0.035, 0.035], "P2": [0.015, 0.015, 0.015], "P4": [0.055, 0.055, 0.055]}


def scatter_run(n=30, seed=0, sigma=(10 * UM,) * 3 + (3.6 * ARCSEC,) * 3, tool_in_opr=None, points=POINTS):
    """Measured = true poses (no instrument error) scattered around a commanded pose per point."""
    rng = np.random.default_rng(seed)
    measured, commanded = {}, {}
    for name, position in points.items():
        commanded[name] = np.array([*position, 0.0, 0.0, 0.0])
        measured[name] = commanded[name] + 50 * UM * rng.normal(size=6) * [1, 1, 1, 0, 0, 0] \
            + rng.normal(size=(n, 6)) * sigma
    return IsoRun(measured=measured, commanded=commanded, tool_in_opr=tool_in_opr)


def term(name, correlation, u, **kwargs):
    return BudgetTerm(name, "test", correlation, u, **kwargs)


def only(*terms):
    return UncertaintyBudget(tuple(terms))


# -- pose arithmetic -------------------------------------------------------------------------------


def test_rotation_helpers_match_instrument_pose():
    rng = np.random.default_rng(1)
    for _ in range(20):
        opr = np.concatenate([rng.normal(size=3) * 0.05, rng.uniform(-1.2, 1.2, size=3)])
        tool = np.concatenate([rng.normal(size=3) * 0.1, rng.uniform(-1.0, 1.0, size=3)])
        expected = (Pose.from_euler(opr[:3], opr[3:]) @ Pose.from_euler(tool[:3], tool[3:])).as_iso()
        rotation, translation = euler_to_matrix(tool[3:]), tool[:3]
        got = compose(opr, rotation, translation)
        np.testing.assert_allclose(got, expected, atol=1e-12)
        np.testing.assert_allclose(decompose(got, rotation, translation), opr, atol=1e-12)
        np.testing.assert_allclose(matrix_to_euler(euler_to_matrix(opr[3:])), opr[3:], atol=1e-12)


# -- budget terms ----------------------------------------------------------------------------------


def test_term_validation_names_the_field():
    with pytest.raises(UncertaintyError, match="term 'x': standard_uncertainty must be ≥ 0"):
        term("x", "pose", [-1, 0, 0, 0, 0, 0])
    with pytest.raises(UncertaintyError, match="correlation: expected one of pose, point, run, scale"):
        term("x", "per-pose", [1] * 6)
    with pytest.raises(UncertaintyError, match="dof must be ≥ 3"):
        term("x", "pose", [1] * 6, dof=2)
    with pytest.raises(UncertaintyError, match="expected 6 values"):
        term("x", "pose", [1, 2, 3])
    with pytest.raises(UncertaintyError, match="unknown component"):
        compensation_term({"q": 1e-6})
    with pytest.raises(UncertaintyError, match="validity.x: expected lo < hi"):
        compensation_term({"x": 1e-6}, validity={"x": (0.07, 0.0)})
    with pytest.raises(UncertaintyError, match="point terms only"):
        term("x", "run", [1] * 6, validity=[(0, 1)] * 6)
    with pytest.raises(UncertaintyError, match="repeated: noise"):
        only(term("noise", "pose", [1] * 6), term("noise", "run", [1] * 6))


def test_budget_round_trips_through_json():
    budget = only(
        frame_noise_from_calibration({"x": 1e-6, "a": 5e-6}, dof=90),
        compensation_term({"x": 1e-6, "b": 2e-6}, validity={"x": (0, 0.07), "b": (-0.03, 0.03)},
                          correlation_length={"x": 0.005}, dof=13),
        *interferometer_terms(0.3e-6, 0.1e-6, correlation_length=0.005),
        rotary_table_term(1e-6),
        transform_term(2e-6, 6, spread=0.03, lever=0.03),
        environment_term(0.5, 11.5e-6, 0.05, temperature_uncertainty=0.1),
    )
    again = UncertaintyBudget.from_dict(json.loads(json.dumps(budget.to_dict())))
    assert again == budget


def test_compensation_term_removes_the_noise_floor_in_quadrature():
    t = compensation_term({"x": 1.2e-6, "y": 1.0e-6}, noise_floor={"x": 1.1e-6, "y": 1.1e-6}, observations_per_point=9)
    assert t.standard_uncertainty[0] == pytest.approx(math.sqrt(1.2e-6**2 - 1.1e-6**2))
    assert t.standard_uncertainty[1] == pytest.approx(1.1e-6 / 3)  # held-out below the floor: the fit's own noise
    assert compensation_term({"x": 1.2e-6}).standard_uncertainty[0] == 1.2e-6  # no floor given: conservative


def test_compensation_term_grows_outside_its_validity_range():
    t = compensation_term({"x": 1e-6, "a": 2e-6}, validity={"x": (0.0, 0.07), "a": (-0.03, 0.03)},
                          correlation_length={"x": 0.005, "a": 0.004}, outside_factor=2.0)
    values = np.array([[0.035, 0, 0, 0.0, 0, 0], [0.08, 0, 0, 0.04, 0, 0]])
    u = t.uncertainty_at(values)
    assert u[0, 0] == pytest.approx(1e-6) and u[0, 3] == pytest.approx(2e-6)
    assert u[1, 0] == pytest.approx(1e-6 * (2 + 0.01 / 0.005))  # 10 mm beyond, ℓ = 5 mm
    assert u[1, 3] == pytest.approx(2e-6 * (2 + 0.01 / 0.004))


def test_transform_and_environment_terms():
    t = transform_term(2e-6, 6, spread=0.03, lever=0.03)
    sigma = math.sqrt(6 * 4e-12 / 12)
    assert t.standard_uncertainty[0] == pytest.approx(sigma / math.sqrt(6) * math.sqrt(2))
    assert t.standard_uncertainty[3] == pytest.approx(sigma / (math.sqrt(6) * 0.03))
    e = environment_term(0.6, 10e-6, 0.5, temperature_uncertainty=0.2)
    assert e.standard_uncertainty[:3] == pytest.approx((10e-6 * 0.5 * math.sqrt(0.12 + 0.04),) * 3)
    assert e.standard_uncertainty[3:] == (0.0, 0.0, 0.0)
    with pytest.raises(UncertaintyError, match="≥ 3 points"):
        transform_term(1e-6, 2, spread=0.03)


# -- frame noise estimators ------------------------------------------------------------------------


def test_frame_noise_from_frames_recovers_the_noise():
    rng = np.random.default_rng(2)
    sigma = np.array([1e-6, 2e-6, 0.5e-6, 5e-6, 4e-6, 6e-6])
    poses = rng.normal(size=(200, 1, 6)) * 1e-4  # the robot's scatter between poses must not count
    frames = poses + rng.normal(size=(200, 3, 6)) * sigma
    single = frame_noise_from_frames(frames, averaged=False)
    assert single.dof == 400 and single.correlation is Correlation.POSE
    np.testing.assert_allclose(single.standard_uncertainty, sigma, rtol=0.12)
    averaged = frame_noise_from_frames(frames)
    np.testing.assert_allclose(averaged.standard_uncertainty, np.array(single.standard_uncertainty) / math.sqrt(3))
    with pytest.raises(UncertaintyError, match="identical frames"):
        frame_noise_from_frames(np.repeat(poses, 2, axis=1))
    with pytest.raises(UncertaintyError, match="k ≥ 2"):
        frame_noise_from_frames(poses)


def test_frame_noise_from_residuals_matches_the_scatter_of_least_squares_solutions():
    """A linear least-squares problem with 12 observations of 6 unknowns: the estimator's u must
    match the actual scatter of the solutions."""
    rng = np.random.default_rng(3)
    jacobian = rng.normal(size=(12, 6)) * [1, 1, 1, 0.3, 0.3, 0.3]
    sigma = 2e-6
    solutions, rms = [], []
    for _ in range(3000):
        noise = rng.normal(size=12) * sigma
        p, *_ = np.linalg.lstsq(jacobian, noise, rcond=None)
        residual = noise - jacobian @ p
        solutions.append(p)
        rms.append(np.sqrt(np.mean(residual**2)))
    estimate = frame_noise_from_residuals(np.array(rms), jacobian)
    np.testing.assert_allclose(estimate.standard_uncertainty, np.std(solutions, axis=0), rtol=0.05)
    assert estimate.dof == 3000 * 6
    with pytest.raises(UncertaintyError, match="singular"):
        frame_noise_from_residuals(rms, np.zeros((12, 6)))
    with pytest.raises(UncertaintyError, match="expected \\(12, 6\\)"):
        frame_noise_from_residuals(rms, np.zeros((10, 6)))


# -- propagation: analytic cases ---------------------------------------------------------------------


def test_plain_value_is_the_iso_formula_and_the_intervals_are_iso9283s():
    run = scatter_run()
    result = iso_uncertainty(run, only(frame_noise_from_calibration({"x": 1e-6}, 90)), draws=100, contributions=False)
    p1 = result.points["P1"]
    rp = pose_repeatability(run.measured["P1"], confidence=0.95)
    ap = pose_accuracy(run.measured["P1"], run.commanded["P1"], confidence=0.95)
    assert p1["rp_l"].uncorrected_value == rp.rp_l and p1["ap_x"].uncorrected_value == ap.ap_x
    assert p1["rp_l"].confidence_interval == rp.rp_l_ci and p1["ap_a"].confidence_interval == ap.ap_a_ci
    assert p1["ap_x"].confidence_interval is None  # iso9283 computes none for AP_x
    assert result.draws == 100 and result.seed == 0


@pytest.mark.parametrize("kind, u, expected", [
    ("run", 2e-6, 2e-6),  # one offset for the run: fully in the barycentre
    ("point", 2e-6, 2e-6),  # systematic at the point: fully in the barycentre
    ("pose", 2e-6, 2e-6 / math.sqrt(30)),  # independent per pose: averaged over n = 30
])
def test_ap_x_uncertainty_follows_the_correlation(kind, u, expected):
    result = iso_uncertainty(scatter_run(), only(term("t", kind, [u, 0, 0, 0, 0, 0])), draws=2000, contributions=False)
    for point in POINTS:
        assert result.points[point]["ap_x"].standard_uncertainty == pytest.approx(expected, rel=0.06)
        assert result.points[point]["ap_y"].standard_uncertainty == 0.0


def test_scale_term_acts_in_proportion_to_the_coordinate():
    result = iso_uncertainty(scatter_run(), only(interferometer_terms(1e-4, 0.0)[0]), draws=2000, contributions=False)
    for point, position in POINTS.items():
        # rectangular, shared by x, y, z: u(AP_x) = u_s · x exactly (the same draw scales every pose)
        assert result.points[point]["ap_x"].standard_uncertainty == pytest.approx(1e-4 * position[0], rel=0.05)


def test_an_angle_error_reaches_the_tool_point_through_its_lever():
    """Noise on the OPR's b (rotation about y) moves a tool point 0.1 m along z by 0.1·δb in x."""
    run = scatter_run(tool_in_opr=[0, 0, 0.1, 0, 0, 0])
    sigma_b = 10 * ARCSEC
    result = iso_uncertainty(run, only(term("noise", "pose", [0, 0, 0, 0, sigma_b, 0])), draws=2000,
                             contributions=False)
    p1 = result.points["P1"]
    assert p1["ap_b"].standard_uncertainty == pytest.approx(sigma_b / math.sqrt(30), rel=0.06)
    assert p1["ap_x"].standard_uncertainty == pytest.approx(0.1 * sigma_b / math.sqrt(30), rel=0.06)
    without_lever = iso_uncertainty(scatter_run(), only(term("noise", "pose", [0, 0, 0, 0, sigma_b, 0])), draws=200,
                                    contributions=False)
    assert without_lever.points["P1"]["ap_x"].standard_uncertainty == 0.0


def test_each_correlation_moves_only_the_figures_its_physics_allows():
    """A run offset cannot move a spread or a difference; a per-point error cancels between the
    approach directions of one point but not between two points; per-pose noise moves all."""
    run = scatter_run(n=12)
    rng = np.random.default_rng(5)
    p1 = run.measured["P1"]
    directions = {"P1": [p1, p1.mean(axis=0) + rng.normal(size=(12, 6)) * 10 * UM * [1, 1, 1, 0, 0, 0]]}
    run = IsoRun(run.measured, run.commanded, directions=directions)
    budget = only(term("noise", "pose", [1e-6] * 6), term("curve", "point", [1e-6] * 6),
                  term("offset", "run", [1e-6] * 6))
    result = iso_uncertainty(run, budget, draws=100, distance_pairs=[("P2", "P4")], drift_cycles=4,
                             contribution_draws=100)
    contributions = {(g, o, f.name): f.contributions for g, o, f in result.figures()}
    for key, c in contributions.items():
        name = key[2]
        assert c["noise"] > 0, key
        # "Moves" = more than 0.1 % of the noise's share: a cancelled term leaves rounding (~1e-13) or a
        # second-order trace (a per-point offset turns the P2–P4 distance by ~1e-4 rad: RD_p moves ~1e-4).
        floor = 1e-3 * c["noise"]
        # dAP_p = AP_P(first) − AP_P(last) is a difference of norms: an offset shifts both vectors
        # but changes their lengths differently; the signed dAP_a/b/c cancel it exactly.
        moved_by_offset = name.startswith("ap_") or name == "dap_p"
        assert (c["offset"] > floor) == moved_by_offset, key
        moved_by_curve = moved_by_offset or name.startswith("ad_")  # not RP, dRP, RD, nor vAP at one point
        assert (c["curve"] > floor) == moved_by_curve, key


def test_noise_bias_of_a_repeatability_is_corrected():
    """RP_a of a scatter σ_r measured with noise σ reads 3·√(σ_r² + σ²): the corrected value comes
    back to the truth on average, the uncorrected one does not (and carries the bias in U)."""
    sigma_r, sigma = 3.6 * ARCSEC, 1.8 * ARCSEC
    corrected, uncorrected, true = [], [], []
    for seed in range(40):
        rng = np.random.default_rng(seed)
        truth = rng.normal(size=(30, 6)) * sigma_r
        measured = truth + rng.normal(size=(30, 6)) * sigma
        run = IsoRun({"P1": measured}, {"P1": np.zeros(6)}, truth={"P1": truth})
        budget = only(term("frame noise", "pose", [sigma] * 6))
        f = iso_uncertainty(run, budget, draws=200, seed=seed, contributions=False).points["P1"]["rp_a"]
        kept = iso_uncertainty(run, budget, draws=200, seed=seed, contributions=False, correct_bias=False)
        g = kept.points["P1"]["rp_a"]
        assert g.value == g.uncorrected_value == f.uncorrected_value
        assert g.expanded_uncertainty == pytest.approx(2 * g.standard_uncertainty + abs(g.noise_bias))
        corrected.append(f.value)
        uncorrected.append(f.uncorrected_value)
        true.append(f.true)
    bias = 3 * (math.sqrt(sigma_r**2 + sigma**2) - sigma_r)
    assert np.mean(uncorrected) - np.mean(true) == pytest.approx(bias, rel=0.35)
    assert abs(np.mean(corrected) - np.mean(true)) < 0.25 * bias


def test_outside_the_validity_range_is_flagged_and_costs_uncertainty():
    term_ = compensation_term({"x": 1e-6}, validity={"x": (0.0, 0.05)}, correlation_length={"x": 0.005})
    result = iso_uncertainty(scatter_run(), only(term_), draws=1000, contributions=False)
    assert dict(result.outside_validity) == {"P4": ("x",)}  # P4 at x = 55 mm, 5 mm beyond
    assert result.points["P1"]["ap_x"].standard_uncertainty == pytest.approx(1e-6, rel=0.07)
    assert result.points["P4"]["ap_x"].standard_uncertainty == pytest.approx(3e-6, rel=0.07)  # u·(2 + 5/5)


def test_export_shape():
    run = scatter_run()
    run = IsoRun(run.measured, run.commanded, truth=run.measured)
    budget = only(frame_noise_from_calibration(dict.fromkeys("xyzabc", 1e-06), 90), term("offset", "run", [2e-6] * 6))
    result = iso_uncertainty(run, budget, draws=100, distance_pairs=[("P2", "P4")], drift_cycles=10,
                             contribution_draws=60)
    exported = json.loads(json.dumps(result.to_dict()))  # plain JSON, no numpy types
    assert exported["coverage_factor"] == 2 and isinstance(exported["coverage_factor"], int)
    assert exported["bias_policy"] == "corrected" and len(exported["budget"]["terms"]) == 2
    names = {"rp_l", "rp_a", "rp_b", "rp_c", "ap_p", "ap_x", "ap_y", "ap_z", "ap_a", "ap_b", "ap_c", "dap_p",
             "dap_a", "dap_b", "dap_c", "drp_l", "drp_a", "drp_b", "drp_c"}
    for point in POINTS:
        assert set(exported["points"][point]) == names
        for figure in exported["points"][point].values():
            assert {"value", "expanded_uncertainty", "coverage_factor", "confidence_interval", "true",
                    "budget"} <= set(figure)
            assert figure["coverage_factor"] == 2 and figure["expanded_uncertainty"] >= 0
            assert set(figure["budget"]["contributions"]) == {"frame noise", "offset"}
    rp_l = exported["points"]["P1"]["rp_l"]
    assert rp_l["confidence_interval"][0] < rp_l["budget"]["uncorrected_value"] < rp_l["confidence_interval"][1]
    assert rp_l["true"] == pytest.approx(pose_repeatability(run.measured["P1"]).rp_l)
    assert set(exported["distances"]["P2-P4"]) >= {"ad_p", "rd_p", "ad_a", "rd_c"}


def test_the_25_percent_rule_is_flagged_per_figure():
    run = scatter_run()
    budget = only(term("offset", "run", [2e-6, 2e-6, 2e-6, 0, 0, 0]))
    result = iso_uncertainty(run, budget, draws=400, contributions=False, characteristics={"ap_y": 1e-6})
    p1 = result.points["P1"]
    assert p1["ap_p"].meets_25_percent_rule  # ≈ 85 µm against U ≈ 4 µm
    assert p1["ap_x"].ratio == pytest.approx(p1["ap_x"].expanded_uncertainty / abs(p1["ap_x"].value))
    assert not p1["ap_y"].meets_25_percent_rule and p1["ap_y"].characteristic == 1e-6
    assert ("points", "P1", "ap_y") in result.above_25_percent()
    assert ("points", "P1", "ap_p") not in result.above_25_percent()


def test_results_are_seeded():
    run = scatter_run(n=8)
    budget = only(frame_noise_from_calibration(dict.fromkeys("xyzabc", 1e-06), 90))
    first = iso_uncertainty(run, budget, draws=80, seed=3, contribution_draws=50).to_dict()
    assert iso_uncertainty(run, budget, draws=80, seed=3, contribution_draws=50).to_dict() == first
    assert iso_uncertainty(run, budget, draws=80, seed=4, contribution_draws=50).to_dict() != first


def test_drift_is_propagated_signed_and_reported_as_a_magnitude():
    run = scatter_run(n=5, points={"P1": [0.03, 0.03, 0.03]})
    budget = only(term("noise", "pose", [1e-6] * 6))
    result = iso_uncertainty(run, budget, draws=100, drift_cycles=2, contributions=False)
    drift = result.points["P1"]["drp_l"]
    assert drift.value >= 0 and drift.uncorrected_value >= 0 and drift.mc_interval[0] >= 0
    short = iso_uncertainty(run, budget, draws=100, drift_cycles=3, contributions=False)
    assert "drp_l" not in short.points["P1"] and "P1: no drift figures" in short.notes[0]


@pytest.mark.parametrize("change, message", [
    (dict(measured={"P1": np.zeros((5, 3))}), r"measured\['P1'\]: expected \(n ≥ 2, 6\) poses"),
    (dict(measured={"P1": np.full((5, 6), np.nan)}), "non-finite"),
    (dict(commanded={}), "no commanded pose for point 'P1'"),
    (dict(tool_in_opr=np.eye(3)), "tool_in_opr: expected a \\(6,\\) pose"),
    (dict(tool_in_opr=2 * np.eye(4)), "not a rotation matrix"),
    (dict(truth={"P1": np.zeros((4, 6))}), r"truth\['P1'\]: 4 poses for 5 measured ones"),
    (dict(directions={"P9": [np.zeros((3, 6))] * 2}), "unknown point 'P9'"),
])
def test_bad_run_input_is_one_clear_line(change, message):
    base = dict(measured={"P1": np.zeros((5, 6))}, commanded={"P1": np.zeros(6)})
    with pytest.raises(UncertaintyError, match=message) as info:
        iso_uncertainty(IsoRun(**(base | change)), only(), draws=50)
    assert "\n" not in str(info.value)


def test_bad_options_are_one_clear_line():
    run = scatter_run(n=4)
    with pytest.raises(UncertaintyError, match="draws: expected an integer ≥ 50"):
        iso_uncertainty(run, only(), draws=10)
    with pytest.raises(UncertaintyError, match="unknown point"):
        iso_uncertainty(run, only(), draws=50, distance_pairs=[("P1", "P7")])
    with pytest.raises(UncertaintyError, match="budget: expected an UncertaintyBudget"):
        iso_uncertainty(run, [term("x", "pose", [1] * 6)], draws=50)  # type: ignore[arg-type]


# -- a calibration's residual --------------------------------------------------------------------


def test_calibration_residual_uncertainty_covers_the_residual_against_truth():
    """Held-out residuals measured against a noisy reference: the RMS is inflated by the reference's
    noise; the corrected value and U cover the RMS against the truth."""
    covered, bias_before, bias_after = 0, [], []
    for seed in range(40):
        rng = np.random.default_rng(seed)
        points = np.repeat(np.arange(13), 9)
        reference_value = np.repeat(np.linspace(0.005, 0.065, 13), 9)
        true_residual = rng.normal(size=13)[points] * 0.3 * UM + rng.normal(size=points.size) * 0.4 * UM
        measured_residual = true_residual - rng.normal(size=points.size) * 0.5 * UM  # the reference's noise
        f = calibration_residual_uncertainty(measured_residual, reference_value, points, component="x",
                                             reference_noise=0.5 * UM, reference_scale=1e-6, draws=2000, seed=seed,
                                             true_residuals=true_residual, characteristic=1.5 * UM)
        covered += abs(f.value - f.true) <= f.expanded_uncertainty
        bias_before.append(f.uncorrected_value - f.true)
        bias_after.append(f.value - f.true)
        assert f.confidence_interval[0] < f.uncorrected_value < f.confidence_interval[1]
        assert set(f.contributions) == {"reference noise", "reference scale"}
    assert covered >= 34  # of 40 (≈ 95 % expected)
    assert np.mean(bias_before) > 0.08 * UM and abs(np.mean(bias_after)) < 0.3 * np.mean(bias_before)
    with pytest.raises(UncertaintyError, match="component"):
        calibration_residual_uncertainty([1.0], [1.0], [0], component="q")
    with pytest.raises(UncertaintyError, match="points: expected 2 labels"):
        calibration_residual_uncertainty([1.0, 2.0], [1.0, 2.0], [0], component="x")


def test_iso_uncertainty_reports_how_far_it_is():
    """``progress(k, n)`` after each Monte Carlo pass: the budget's, then one per active term; same result."""
    budget = only(term("noise", "pose", [1 * UM, 0, 0, 0, 0, 0]), term("scale", "pose", [0, 1 * UM, 0, 0, 0, 0]),
                  term("off", "pose", [0, 0, 0, 0, 0, 0]))  # inactive: no pass
    calls: list[tuple[int, int]] = []
    with_progress = iso_uncertainty(scatter_run(n=10), budget, draws=60, contribution_draws=50,
                                    progress=lambda k, n: calls.append((k, n)))
    assert calls == [(1, 3), (2, 3), (3, 3)]
    without = iso_uncertainty(scatter_run(n=10), budget, draws=60, contribution_draws=50)
    assert with_progress.to_dict() == without.to_dict()
