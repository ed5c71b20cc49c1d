"""instrument.compensation: data, CSF, alignment, CSF-PPSO-ESN and baselines against known curves."""

import numpy as np
import pytest
from scipy.interpolate import make_smoothing_spline

from instrument.compensation import (
    ARCSEC,
    CalibrationData,
    CsfPpsoEsnCompensator,
    EsnHyperparameters,
    FittedModel,
    GaussianProcessCompensator,
    NoCompensation,
    ParetoResult,
    PolynomialCompensator,
    RippleSplineCompensator,
    SmoothingSplineCompensator,
    align_groups,
    features,
    fit_spline_curve,
    hard_campaign,
    joint_fit,
    make_reservoir,
    noise_floor,
    paper_like_scenario,
    point_means,
    synthetic_calibration,
    tune_csf_esn,
)

UM = 1e-6


@pytest.fixture(scope="module")
def scenario():
    return paper_like_scenario(seed=3)


def fast_methods(seed=0):
    return {
        "csf-ppso-esn": CsfPpsoEsnCompensator(seed=seed, n_particles=8, n_iterations=6),
        "csf": SmoothingSplineCompensator(),
        "csf+ripple": RippleSplineCompensator(),
        "polynomial": PolynomialCompensator(),
        "gaussian_process": GaussianProcessCompensator(),
        "none": NoCompensation(),
    }


def test_scenario_matches_the_paper_design(scenario):
    x, a = scenario.data["x"], scenario.data["a"]
    assert x.n_points == 15 and np.unique(x.group).size == 3 and x.measured.size == 135
    assert x.reference.min() == pytest.approx(0.0, abs=20 * UM)
    assert x.reference.max() == pytest.approx(0.07, abs=20 * UM)
    for c in "xyz":
        assert 30 * UM < np.abs(scenario.data[c].error).max() < 100 * UM
    for c in "abc":
        assert 15 * ARCSEC < np.abs(scenario.data[c].error).max() < 50 * ARCSEC
    # the pooled repeat scatter is the simulated noise (135 − 45 degrees of freedom: ±15 %)
    assert noise_floor(x.error, x.group, x.point) == pytest.approx(scenario.noise_sigma["x"], rel=0.2)
    assert noise_floor(a.error, a.group, a.point) == pytest.approx(scenario.noise_sigma["a"], rel=0.2)


def test_calibration_data_validates_its_arrays():
    with pytest.raises(ValueError, match="one length"):
        CalibrationData("x", [0.0, 1.0], [0.0], [0, 0], [0, 1])
    with pytest.raises(ValueError, match="unknown pose component"):
        CalibrationData("q", [0.0], [0.0], [0], [0])
    with pytest.raises(ValueError, match="finite"):
        CalibrationData("x", [np.nan], [0.0], [0], [0])
    with pytest.raises(ValueError, match="direction must be"):
        CalibrationData("x", [0.0, 0.01], [0.0, 0.01], direction=[1, 0])


def test_passing_the_error_for_the_reference_is_refused(scenario):
    """One input convention: measured + reference. The error in either slot is caught, not fitted."""
    data = scenario.data["x"]
    with pytest.raises(ValueError, match="pass the reference instrument's reading as 'reference', not the error"):
        CalibrationData("x", data.measured, data.error, data.group, data.point)
    with pytest.raises(ValueError, match="not the error"):
        CalibrationData("x", data.error, data.reference, data.group, data.point)
    with pytest.raises(TypeError, match="takes CalibrationData"):
        SmoothingSplineCompensator().fit(data.measured)  # type: ignore[arg-type]


def test_calibration_data_defaults_and_directions(scenario):
    data = scenario.data["y"]
    bare = CalibrationData("y", data.measured, data.reference)
    assert np.all(bare.group == 0) and bare.n_points == 15 and bare.directions == () and not bare.bidirectional
    both = CalibrationData("y", data.measured, data.reference, direction=np.where(data.point % 2, 1, -1))
    assert both.directions == (-1, 1) and both.bidirectional
    assert both.subset(both.direction == 1).directions == (1,)
    summary = both.summary()
    assert summary["n_observations"] == 135 and summary["directions"] == [-1, 1] and len(summary["data_sha256"]) == 64
    assert summary["data_sha256"] != bare.summary()["data_sha256"]


def test_log_grid_gcv_spline_recovers_a_short_low_noise_curve():
    rng = np.random.default_rng(11)
    x = np.linspace(0.0, 0.07, 15)
    truth = lambda v: 50 * UM * np.sin(v / 0.02) + 20 * UM * (v / 0.07) ** 2
    sigma_mean = 0.25 * UM
    y = truth(x) + rng.normal(0.0, sigma_mean, x.size)
    fine = np.linspace(0.0, 0.07, 701)
    for criterion in ("gcv", "loo"):
        for end_curvature in (False, True):
            curve = fit_spline_curve(x, y, np.ones(15), criterion=criterion, end_curvature=end_curvature)
            # between the points the curve is as good as the noise of the means allows
            assert np.abs(curve.predict(fine) - truth(fine)).max() < 5 * sigma_mean
    # the pitfall this guards against: scipy's own λ search over-smooths this curve
    scipy_curve = make_smoothing_spline(x, y)
    assert np.abs(scipy_curve(fine) - truth(fine)).max() > 5 * sigma_mean


def test_end_curvature_lets_the_ends_bend():
    """Natural end conditions force g'' = 0 at the ends; the unpenalised u² term lets them bend.

    Heavily smoothed, the natural spline of a quadratic becomes a straight line and misses the ends
    by tens of µm, the partial spline becomes the least-squares quadratic. With λ by GCV the gain is
    smaller but systematic: over 20 noise draws of a quadratic, the mean error is lower."""
    x = np.linspace(-1.0, 1.0, 15)
    truth = lambda v: 40 * UM * v**2
    fine = np.linspace(-1.0, 1.0, 301)
    ends = np.abs(fine) >= x[-2]
    rng = np.random.default_rng(2)
    y = truth(x) + rng.normal(0.0, 2 * UM, x.size)
    natural = fit_spline_curve(x, y, lam=1e6)
    bending = fit_spline_curve(x, y, lam=1e6, end_curvature=True)
    assert np.abs(natural.predict(fine[ends]) - truth(fine[ends])).max() > 10 * UM
    assert np.abs(bending.predict(fine[ends]) - truth(fine[ends])).max() < 2 * UM
    assert bending.curvature == pytest.approx(40 * UM, rel=0.1)
    errors = {False: [], True: []}
    for seed in range(20):
        y = truth(x) + np.random.default_rng(seed).normal(0.0, 2 * UM, x.size)
        for end_curvature in errors:
            curve = fit_spline_curve(x, y, end_curvature=end_curvature)
            errors[end_curvature].append(np.sqrt(np.mean((curve.predict(fine) - truth(fine)) ** 2)))
    assert np.mean(errors[True]) < 0.95 * np.mean(errors[False])


def test_spline_continues_linearly_beyond_the_knots():
    x = np.linspace(0, 1, 8)
    for end_curvature in (False, True):
        curve = fit_spline_curve(x, x**2, np.ones(8), end_curvature=end_curvature)
        slope = (curve.predict(1.0) - curve.predict(1.0 - 1e-6)) / 1e-6
        assert curve.predict(1.5) == pytest.approx(curve.predict(1.0) + 0.5 * slope, rel=1e-4)


def test_group_alignment_recovers_the_offsets(scenario):
    hard = hard_campaign(0, "y")  # offsets of tens of µm
    cases = [(scenario.data[c], scenario.group_offsets[c], scenario.noise_sigma[c]) for c in ("x", "b")]
    cases.append((hard.calibration, hard.group_offsets, hard.noise_sigma))
    for data, true, sigma in cases:
        alignment = align_groups(data.measured, data.error, data.group, data.point)
        for g in (1, 2):
            # offset = −(group's extra error); ~15 observations per group in the interval
            assert alignment.offset(g) == pytest.approx(-(true[g] - true[0]), abs=4 * sigma)
        lo, hi = alignment.interval
        assert data.measured.min() <= lo < hi <= data.measured.max()
        assert alignment.offset(0) == 0.0


def test_fitted_models_follow_the_true_error(scenario):
    data = scenario.data["y"]
    fine = np.linspace(0.0, 0.07, 301)
    truth = scenario.true_error["y"](fine)
    for name, method in fast_methods().items():
        model = method.fit(data)
        worst = np.abs(model.predict(fine) - truth).max()
        if name == "none":
            assert worst > 20 * UM
        elif name == "polynomial":
            assert worst < 5 * UM
        else:
            assert worst < 1.5 * UM, name


def test_points_can_be_inferred_from_measured_values(scenario):
    data = scenario.data["x"]
    with_labels = SmoothingSplineCompensator().fit(data)
    inferred = SmoothingSplineCompensator().fit(CalibrationData("x", data.measured, data.reference, data.group))
    np.testing.assert_allclose(inferred.predict(data.measured), with_labels.predict(data.measured), atol=1e-12)


def test_csf_esn_held_out_objective_equals_refits_without_each_point(scenario):
    """The PPSO's held-out objective (closed form) is an explicit refit without each point's data."""
    data = scenario.data["c"]
    xm, em, wm, _ = point_means(data.measured, data.error, data.point)
    u = 2 * (xm - xm.min()) / np.ptp(xm) - 1
    y = em / np.std(em)
    hyper = EsnHyperparameters(30, 0.8, 0.5, 1.0, 1e-3, 1e-4)
    reservoir = make_reservoir(30, 0.8, 7)
    phi = features(reservoir, u, hyper)
    from instrument.compensation._spline import PartialSpline

    full = joint_fit(PartialSpline(u, wm), y, phi, hyper)
    loo = full.loo_residuals(y)
    mu = hyper.ridge * np.trace(phi @ phi.T) / u.size
    for i in range(1, u.size - 1):
        keep = np.arange(u.size) != i
        # the same objective on the other points: weights renormalise to mean 1, so λ and μ scale with it
        scale = wm.mean() / wm[keep].mean()
        ridge = mu * scale * keep.sum() / np.trace(phi[keep] @ phi[keep].T)
        refit_hyper = EsnHyperparameters(30, 0.8, 0.5, 1.0, ridge, hyper.smoothing * scale)
        refit = joint_fit(PartialSpline(u[keep], wm[keep]), y[keep], phi[keep], refit_hyper)
        from instrument.compensation import CsfEsnCurve

        curve = CsfEsnCurve(refit_hyper, reservoir, 0.0, 1.0, 1.0, u[keep], refit.spline_values, refit.curvature,
                            refit.weights, 7)
        assert y[i] - curve.predict(u[i : i + 1])[0] == pytest.approx(loo[i], rel=1e-6, abs=1e-9)


def test_model_choice_in_the_objectives_own_unit():
    """min_heldout and ideal_point choose on the front; one_se takes, among every evaluated model within
    one standard error of the best held-out RMS, the one with the fewest effective degrees of freedom."""
    from instrument.compensation._csf_esn import SwarmLog, select

    # training RMS barely varies, held-out RMS spans decades (the failure mode)
    f = np.array([[0.000, 5.0], [0.001, 0.50], [0.002, 0.21], [0.003, 0.20]])
    front = ParetoResult(np.arange(4.0)[:, None], f, 0)
    # two more evaluations, dominated (higher training and held-out RMS) but smoother
    heldout = np.array([5.0, 0.50, 0.21, 0.20, 0.203, 0.30])
    squares = np.tile(0.2**2 + np.linspace(-0.01, 0.01, 13), (6, 1))  # SE of the RMS ≈ 0.0043
    log = SwarmLog(np.arange(6.0)[:, None], np.array([0, 0.001, 0.002, 0.003, 0.004, 0.01]), heldout,
                   np.array([15.0, 14, 12, 10, 8, 4]), squares)
    assert select(front, log, "min_heldout")[0] == 3
    assert select(front, log, "ideal_point")[0] == 3
    assert select(front, log, "one_se")[0] == 4  # 0.203 ≤ 0.20 + SE with 8 dof; 4 dof is 0.30: too far
    with pytest.raises(ValueError, match="selection must be one of"):
        select(front, log, "best")


def test_csf_ppso_esn_is_deterministic_and_never_worse_than_its_csf_start(scenario):
    data = scenario.data["a"]
    fit = lambda seed: CsfPpsoEsnCompensator(seed=seed, n_particles=8, n_iterations=6).fit(data)
    first, second = fit(4), fit(4)
    np.testing.assert_array_equal(first.predict(data.measured), second.predict(data.measured))
    assert first.details["hyperparameters"] == second.details["hyperparameters"]
    assert fit(5).details["hyperparameters"] != first.details["hyperparameters"]
    # the swarm starts at the CSF alone: what it keeps is at least as good on its own held-out objective
    xm, em, wm, _ = point_means(data.measured, data.error, data.point)
    tuning = tune_csf_esn(xm, em, wm, seed=1, n_particles=6, n_iterations=4, selection="min_heldout")
    csf_loo = []
    for i in range(1, xm.size - 1):
        keep = np.arange(xm.size) != i
        refit = fit_spline_curve(xm[keep], em[keep], wm[keep], end_curvature=True)
        csf_loo.append(em[i] - refit.predict(xm[i : i + 1])[0])
    assert tuning.heldout_rms <= np.sqrt(np.mean(np.square(csf_loo))) * 1.05
    assert tuning.log.positions.shape[0] == tuning.front.n_evaluations == 6 * 5


def test_gaussian_process_length_scale_is_bounded_by_the_grid_step(scenario):
    model = GaussianProcessCompensator().fit(scenario.data["x"])
    assert model.curve.length_scale >= 0.005 * 0.99


def test_every_model_survives_a_dict_round_trip(scenario):
    data = scenario.data["b"]
    bidirectional = hard_campaign(1, "b", hysteresis=True).calibration
    probe = np.linspace(data.measured.min() - 0.001, data.measured.max() + 0.001, 57)
    methods = fast_methods()
    methods["csf+poly2"] = SmoothingSplineCompensator(trend_degree=2)
    methods["csf+ends"] = SmoothingSplineCompensator(end_curvature=True)
    for name, method in methods.items():
        for d in (data, bidirectional):
            model = method.fit(d)
            again = FittedModel.from_dict(model.to_dict())
            for direction in (None, 1, -1):
                np.testing.assert_allclose(again.predict(probe, direction), model.predict(probe, direction),
                                           rtol=1e-12, atol=1e-18)
            assert again.alignment == model.alignment and again.method == model.method == name
            assert again.directions == d.directions


def test_bad_fit_input_is_refused():
    few = CalibrationData("x", [0.0, 0.0, 0.01, 0.02], [0.0, 0.0, 0.01, 0.02], point=[0, 0, 1, 2])
    with pytest.raises(ValueError, match="at least 4 distinct"):
        SmoothingSplineCompensator().fit(few)
    with pytest.raises(ValueError, match="selection must be one of"):
        CsfPpsoEsnCompensator(selection="knee-ish")


def test_single_group_calibration_needs_no_alignment():
    rng = np.random.default_rng(0)
    data = synthetic_calibration("z", np.linspace(0, 0.07, 15), lambda v: 1e-3 * v, repeats=3,
                                 measurement_noise=0.2 * UM, reference_noise=0.1 * UM, rng=rng)
    model = SmoothingSplineCompensator().fit(data)
    assert model.alignment.interval is None
    assert np.abs(model.predict(np.linspace(0, 0.07, 50)) - 1e-3 * np.linspace(0, 0.07, 50)).max() < 0.5 * UM


def _repeated_exactly(n_points: int) -> CalibrationData:
    """Three groups × three repeats of one curve, every repeat bit-identical (a noise floor of 0:
    what a resumed simulated cell that replayed its first session's noise once gave)."""
    x = np.linspace(0.0, 0.07, n_points)
    error = 2 * UM * np.sin(x / 0.07 * 2 * np.pi) + UM * np.random.default_rng(0).normal(size=x.size)
    rows = [(x + error, x, group, np.arange(n_points)) for group in range(3) for _ in range(3)]
    measured, reference, group, point = (np.concatenate([r[i] if i < 2 else np.broadcast_to(r[i], x.shape)
                                                         for r in rows]) for i in range(4))
    return CalibrationData("x", measured, reference, group.astype(int), point.astype(int))


def test_a_zero_noise_floor_still_calibrates():
    from instrument.compensation import calibrate

    data = _repeated_exactly(15)
    assert noise_floor(data.error, data.group, data.point) == 0.0
    record = calibrate({"x": data})  # the GP's noise bounds were log(0): L-BFGS-B raised KeyError (-inf, -inf)
    corrected = record.correct("x", data.measured[:15]).corrected
    assert np.max(np.abs(corrected - data.reference[:15])) < 5 * UM


def test_too_few_points_is_a_typed_one_line_refusal():
    from instrument.compensation import InsufficientCalibrationData, calibrate

    with pytest.raises(InsufficientCalibrationData, match=r"^x: leave-one-point-out needs at least 5 calibration "
                                                          r"points, got 4$"):
        calibrate({"x": _repeated_exactly(4)})
