"""Held-out evaluation: leave-one-point-out and leave-one-group-out against brute force and known truth."""

import numpy as np
import pytest

from instrument.compensation import (
    LOGO,
    LOPO,
    CalibrationData,
    Compensator,
    CsfPpsoEsnCompensator,
    EvaluationTable,
    FittedModel,
    GaussianProcessCompensator,
    GroupAlignment,
    NoCompensation,
    PolynomialCompensator,
    SmoothingSplineCompensator,
    evaluate,
    hard_campaign,
    held_out_residuals,
    paper_like_scenario,
)

UM = 1e-6


@pytest.fixture(scope="module")
def scenario():
    return paper_like_scenario(seed=3)


def brute_force_lopo(compensator, data):
    """Leave each interior point out (all repeats, groups, directions), refit, predict it."""
    order = data.point_order()
    residuals = []
    for held in order[1:-1]:
        test = data.point == held
        train = CalibrationData(data.component, data.measured[~test], data.reference[~test], data.group[~test],
                                data.point[~test], None if data.direction is None else data.direction[~test])
        model = compensator.fit(train)
        predicted = model.predict(data.measured[test], None if data.direction is None else data.direction[test])
        offset = np.array([model.group_offset(g) for g in data.group[test]])
        residuals.append((data.measured[test] - data.reference[test]) - (predicted - offset))
    return np.concatenate(residuals)


@pytest.mark.parametrize("name", ["csf", "csf-ppso-esn"])
def test_leave_one_point_out_matches_brute_force(scenario, name):
    compensator = {"csf": SmoothingSplineCompensator(),
                   "csf-ppso-esn": CsfPpsoEsnCompensator(n_particles=6, n_iterations=4)}[name]
    data = scenario.data["z"]
    row = evaluate({name: compensator}, data, schemes=(LOPO,)).row("z", name)
    explicit = brute_force_lopo(compensator, data)
    assert row.n_heldout == explicit.size == 13 * 9
    assert row.rms == pytest.approx(np.sqrt(np.mean(explicit**2)), rel=1e-12)
    assert row.max_abs == pytest.approx(np.abs(explicit).max(), rel=1e-12)


def test_leave_one_point_out_matches_brute_force_with_directions():
    data = hard_campaign(2, "a", hysteresis=True).calibration
    row = evaluate([SmoothingSplineCompensator()], data, schemes=(LOPO,)).row("a", "csf")
    explicit = brute_force_lopo(SmoothingSplineCompensator(), data)
    assert row.n_heldout == explicit.size == 13 * 3 * 2 * 3
    assert row.rms == pytest.approx(np.sqrt(np.mean(explicit**2)), rel=1e-12)


def test_leave_one_group_out_scores_the_shape_of_a_whole_unseen_group(scenario):
    data = scenario.data["b"]
    compensator = SmoothingSplineCompensator()
    row = evaluate([compensator], data, schemes=(LOGO,)).row("b", "csf", LOGO)
    explicit = []
    for g in (0, 1, 2):
        test = data.group == g
        model = compensator.fit(data.subset(~test))
        r = data.error[test] - model.predict(data.measured[test])
        explicit.append(r - r.mean())
    assert row.rms == pytest.approx(np.sqrt(np.mean(np.concatenate(explicit) ** 2)), rel=1e-12)
    assert row.n_heldout == 135


def test_evaluation_never_scores_on_fitted_points(scenario):
    """A model that memorises its training points and predicts 0 elsewhere must score like none."""

    class Lookup:
        kind = "lookup"

        def __init__(self, x, y):
            self.x, self.y = x, y

        def predict(self, v):
            v = np.atleast_1d(v)
            out = np.zeros(v.shape)
            for i, vi in enumerate(v):
                hit = np.flatnonzero(np.isclose(self.x, vi, rtol=0, atol=1e-12))
                out[i] = self.y[hit[0]] if hit.size else 0.0
            return out

        def to_dict(self):
            return {"kind": self.kind}

    class Memoriser(Compensator):
        name = "memoriser"

        def fit(self, data):
            return FittedModel(self.name, Lookup(data.measured, data.error), GroupAlignment.identity(data.group),
                               (0.0, 1.0))

        def _fit_curve(self, *a):
            raise NotImplementedError

    table = evaluate({"memoriser": Memoriser(), "none": NoCompensation()}, scenario.data["x"], schemes=(LOPO,))
    assert table.row("x", "memoriser").rms == pytest.approx(table.row("x", "none").rms)


def test_every_compensator_cuts_held_out_error_and_the_best_reaches_the_noise_floor(scenario):
    methods = {"csf-ppso-esn": CsfPpsoEsnCompensator(n_particles=6, n_iterations=4),
               "csf": SmoothingSplineCompensator(), "polynomial": PolynomialCompensator(),
               "gaussian_process": GaussianProcessCompensator(), "none": NoCompensation()}
    table = evaluate(methods, {c: scenario.data[c] for c in ("z", "a")})
    text = table.format()
    assert "csf-ppso-esn" in text and LOGO in text and "arcsec" in text and "data sha256" in text
    for component in ("z", "a"):
        raw = table.row(component, "none").rms
        for name in ("csf-ppso-esn", "csf", "polynomial", "gaussian_process"):
            for scheme in (LOPO, LOGO):
                assert table.row(component, name, scheme).rms < raw / 5, (component, name, scheme)
        best = table.row(component, table.best(component))
        assert best.rms < 1.3 * best.noise_floor
        assert best.n_heldout == 13 * 9  # interior points × groups × repeats, each scored once


def test_the_table_says_which_data_it_scored_and_shows_display_units(scenario):
    data = scenario.data["c"]
    table = evaluate([SmoothingSplineCompensator()], data)
    assert table.data["c"] == data.summary()
    row = table.row("c", "csf")
    shown = row.display()
    assert shown["unit"] == "arcsec" and shown["rms"] == pytest.approx(row.rms * 180 * 3600 / np.pi)
    again = EvaluationTable.from_dict(table.to_dict())
    assert again == table


def test_the_record_figure_is_not_optimistic_on_a_hard_campaign():
    """Leave-one-point-out doubles the local step, so it may overstate, never much understate, the
    error the model really makes between calibration points (known truth: fresh off-grid data)."""
    campaign = hard_campaign(3, "x")
    compensator = SmoothingSplineCompensator()
    row = evaluate([compensator], campaign.calibration, schemes=(LOPO,)).row("x", "csf")
    residual, oracle = held_out_residuals(compensator.fit(campaign.calibration), campaign.held_out[0])
    real = np.sqrt(np.mean(residual**2))
    assert 0.9 * real < row.rms < 2.0 * real


def test_too_few_points_for_leave_one_point_out():
    data = CalibrationData("x", np.repeat([0.0, 0.01, 0.02, 0.03], 2), np.repeat([0.0, 0.01, 0.02, 0.03], 2))
    with pytest.raises(ValueError, match="at least 5 calibration points"):
        evaluate([SmoothingSplineCompensator()], data)
    with pytest.raises(ValueError, match="unknown evaluation scheme"):
        evaluate([SmoothingSplineCompensator()], data, schemes=("k-fold",))
