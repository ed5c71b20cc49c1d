"""CalibrationRecord: calibrate(), round trip, format 1 still loading, corruption, and applying corrections."""

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from instrument.compensation import (
    COMPONENTS,
    FORMAT_VERSION,
    LOGO,
    LOPO,
    CalibrationData,
    CalibrationRecord,
    CalibrationRecordError,
    CorrectionResult,
    CsfPpsoEsnCompensator,
    GaussianProcessCompensator,
    NoCompensation,
    PoseCorrection,
    Provenance,
    SmoothingSplineCompensator,
    calibrate,
    hard_campaign,
    paper_like_scenario,
)

PROVENANCE = Provenance(
    run_id="run-2024-001",
    references=({"instrument": "interferometer", "serial": "XL80-0042", "components": ["x"]},
                {"instrument": "rotary table", "serial": "ALIO-7", "components": ["a"]}),
    date="2024-05-02",
    temperature_c=20.4,
)
FORMAT_1 = json.loads((Path(__file__).parent / "data" / "compensation_record_v1.json").read_text(encoding="utf-8"))
FORMAT_2 = json.loads((Path(__file__).parent / "data" / "compensation_record_v2.json").read_text(encoding="utf-8"))


@pytest.fixture(scope="module")
def scenario():
    return paper_like_scenario(seed=5)


@pytest.fixture(scope="module")
def record(scenario):
    methods = {
        "csf-ppso-esn": CsfPpsoEsnCompensator(n_particles=6, n_iterations=4),
        "csf": SmoothingSplineCompensator(),
        "gaussian_process": GaussianProcessCompensator(),
        "none": NoCompensation(),
    }
    return calibrate({c: scenario.data[c] for c in ("x", "a")}, methods, PROVENANCE)


def test_calibrate_needs_nothing_but_the_data(scenario):
    rec = calibrate(scenario.data["y"])
    assert rec.components == ("y",) and rec.provenance == Provenance()
    assert rec.method_for("y") == rec.evaluation.best("y")
    assert {r.method for r in rec.evaluation.rows} == {"csf-ppso-esn", "csf", "csf+ripple", "polynomial",
                                                      "gaussian_process", "none"}
    data = scenario.data["y"]
    residual = rec.correct("y", data.measured).corrected - data.reference  # each group keeps its offset
    residual += rec.models["y"].alignment.offsets_of(data.group)
    assert np.std(residual) < 2 * scenario.noise_sigma["y"] and np.std(data.error) > 20 * scenario.noise_sigma["y"]


def test_record_round_trip_keeps_everything(record):
    text = record.to_json()
    again = CalibrationRecord.from_json(text)
    assert again.to_json() == text and again.content_id == record.content_id == again.source_id
    assert again.provenance == PROVENANCE and again.method == "per-component best"
    assert again.validity == record.validity and again.evaluation == record.evaluation
    probe = np.linspace(0.0, 0.07, 31)
    np.testing.assert_array_equal(again.correct("x", probe).corrected, record.correct("x", probe).corrected)
    payload = json.loads(text)
    assert payload["format_version"] == FORMAT_VERSION == 3 and payload["units"] == {"x": "m", "a": "rad"}
    assert payload["approach_directions"] == {"x": [], "a": []}
    assert payload["methods"] == {c: record.method_for(c) for c in ("x", "a")}
    # the kept method per component is the leave-one-point-out winner, and the record says on what data
    for c in ("x", "a"):
        assert record.method_for(c) == record.evaluation.best(c, LOPO)
        assert payload["evaluation"]["data"][c]["n_observations"] == 135


def test_correct_and_predict_error_share_one_result_convention(record, scenario):
    true_value = np.linspace(0.001, 0.069, 40)
    measured = true_value + scenario.true_error["x"](true_value)
    result = record.correct("x", measured)
    assert isinstance(result, CorrectionResult) and result.ok and result.messages() == []
    assert result.corrected.shape == result.predicted_error.shape == result.out_of_range.shape == (40,)
    np.testing.assert_array_equal(result.corrected, measured - result.predicted_error)
    # group 0's error is the model's frame; the residual is model error only (no noise added here)
    assert np.abs(result.corrected - true_value).max() < 1.5e-6
    grid = record.predict_error("x", measured.reshape(5, 8))
    assert grid.corrected.shape == (5, 8)
    np.testing.assert_array_equal(grid.predicted_error.ravel(), result.predicted_error)
    single = record.correct("x", float(measured[3]))
    assert single.corrected.shape == () and float(single.corrected) == pytest.approx(result.corrected[3], abs=1e-15)


def test_out_of_range_use_is_reported_in_the_result_never_warned(record):
    lo, hi = record.validity["a"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        inside = record.correct("a", 0.5 * (lo + hi))
        outside = record.correct("a", np.array([lo - 0.01, 0.5 * (lo + hi), hi + 0.01]))
        pose = record.correct_pose([0.035, 0.0, 0.0, lo - 0.001, 0.0, 0.2])
    assert inside.ok and not bool(inside.out_of_range)
    np.testing.assert_array_equal(outside.out_of_range, [True, False, True])
    assert "2 value(s) outside the calibrated range" in outside.messages()[0]
    assert isinstance(pose, PoseCorrection)
    np.testing.assert_array_equal(pose.out_of_range, [False, False, False, True, False, False])
    np.testing.assert_array_equal(pose.modelled, [c in ("x", "a") for c in COMPONENTS])
    assert pose.corrected[5] == 0.2 and pose.corrected[0] != 0.035 and pose.predicted_error[1] == 0.0
    assert not pose.ok and len(pose.messages()) == 1 and pose.messages()[0].startswith("a:")


def test_correct_pose_takes_directions_per_component(record):
    pose = [0.035, 0.0, 0.0, 0.0, 0.0, 0.0]
    for direction in (1, [1, None, None, 1, None, None], {"x": 1, "a": 1}):
        result = record.correct_pose(pose, direction)
        # the record is one-directional without a recorded direction: any asked direction is uncovered
        np.testing.assert_array_equal(result.direction_not_covered, [True, False, False, True, False, False])
    assert not record.correct_pose(pose).direction_not_covered.any()
    with pytest.raises(ValueError, match="6 components"):
        record.correct_pose([0.0, 0.0])
    with pytest.raises(ValueError, match="need 6 entries"):
        record.correct_pose(pose, [1, 1])
    with pytest.raises(ValueError, match="unknown pose component"):
        record.correct_pose(pose, {"w": 1})


def test_unknown_components_and_bad_values_are_refused(record):
    with pytest.raises(ValueError, match="no model for component 'y'"):
        record.correct("y", 0.01)
    with pytest.raises(ValueError, match="no model for component 'y'"):
        record.method_for("y")
    with pytest.raises(ValueError, match="must be finite"):
        record.correct("x", np.nan)
    with pytest.raises(ValueError, match="direction must be"):
        record.correct("x", 0.01, direction=2)
    with pytest.raises(ValueError, match="give one direction or one per value"):
        record.correct("x", [0.01, 0.02, 0.03], direction=[1, -1])


def test_a_format_1_record_still_loads_and_corrects_as_before():
    record = CalibrationRecord.from_json(FORMAT_1["record"])
    assert record.source_version == 1 and record.source_id == FORMAT_1["content_id"]
    assert record.content_id != record.source_id  # its content now hashes as the current format
    assert "format-1 evaluation" in record.evaluation.note
    for component, probe in FORMAT_1["probes"].items():
        assert record.method_for(component) == probe["method"] and record.approach_directions(component) == ()
        result = record.correct(component, np.array(probe["measured"]))
        np.testing.assert_allclose(result.corrected, probe["corrected"], rtol=0, atol=1e-15)
        np.testing.assert_array_equal(result.out_of_range, probe["out_of_range"])
    upgraded = CalibrationRecord.from_json(record.to_json())
    assert upgraded.source_version == FORMAT_VERSION and upgraded.content_id == record.content_id
    # its evaluation covered c alone; the k-fold row has no limit, the leave-one-group-out row still counts
    assert set(record.floor_ratios) == {"c"}
    assert all(LOGO in f.heldout_rms and LOPO not in f.heldout_rms for f in record.floor_ratios.values())


def test_a_format_2_record_still_loads_and_corrects_as_before():
    """Written by format 2 (before the ripple term): a CSF-PPSO-ESN curve, GP curves and a hysteresis
    spline correct their probe values as they did, in every approach direction."""
    record = CalibrationRecord.from_json(FORMAT_2["record"])
    assert record.source_version == 2 and record.source_id == FORMAT_2["content_id"] != record.content_id
    for component, probe in FORMAT_2["probes"].items():
        assert record.method_for(component) == probe["method"]
        assert list(record.approach_directions(component)) == probe["directions"]
        for key, direction in (("corrected", None), ("corrected_+1", 1), ("corrected_-1", -1)):
            if key in probe:
                result = record.correct(component, np.array(probe["measured"]), direction=direction)
                np.testing.assert_allclose(result.corrected, probe[key], rtol=0, atol=1e-15)
                np.testing.assert_array_equal(result.out_of_range, probe["out_of_range"])
        floor = record.floor_ratios[component]
        assert set(floor.heldout_rms) == {LOPO, LOGO} and floor.method == probe["method"]
    again = CalibrationRecord.from_json(record.to_json())
    assert again.source_version == FORMAT_VERSION and again.models.keys() == record.models.keys()
    assert json.loads(record.to_json())["noise_floor"]["x"]["ratio"][LOPO] == pytest.approx(
        record.floor_ratios["x"].ratio(LOPO))


def test_the_record_says_how_close_each_component_is_to_the_noise_floor(record):
    """Per component: the kept model's held-out RMS over the pooled repeat scatter, in the JSON too."""
    payload = json.loads(record.to_json())
    for component in ("x", "a"):
        floor = record.floor_ratios[component]
        kept = record.evaluation.row(component, record.method_for(component), LOPO)
        assert floor.method == record.method_for(component) and floor.noise_floor == kept.noise_floor
        assert floor.ratio(LOPO) == pytest.approx(kept.ratio_to_floor)
        assert 0.8 < floor.ratio(LOGO) < 1.3 and floor.at_floor  # paper-like data: every kept model is there
        assert payload["noise_floor"][component]["ratio"][LOPO] == pytest.approx(floor.ratio(LOPO))
        assert payload["noise_floor"][component]["at_floor"] is True
    assert record.floor_messages() == []
    assert "at the noise floor" in record.floor_ratios["x"].message()


def test_a_model_that_misses_a_ripple_is_reported_off_the_floor():
    """The GP alone on a 3-step ripple (issue 25) is not at the floor, and the record says so."""
    data = hard_campaign(0, "y", profile="short-ripple", ripple_period=3.0).calibration
    rec = calibrate(data, {"gaussian_process": GaussianProcessCompensator()})
    floor = rec.floor_ratios["y"]
    assert floor.ratio(LOPO) > 3.0 and not floor.at_floor
    assert rec.floor_messages() == [floor.message()] and "not at the noise floor yet" in floor.message()


def _rehash(payload):
    """Recompute the content id, so only the intended defect remains."""
    import hashlib

    payload.pop("content_id", None)
    canonical = json.dumps(payload, sort_keys=True, separators=(",", ":"), allow_nan=False)
    payload["content_id"] = "sha256:" + hashlib.sha256(canonical.encode("utf-8")).hexdigest()
    return json.dumps(payload)


@pytest.mark.parametrize(
    "corrupt, message",
    [
        (lambda text: text[: len(text) // 2], "not valid JSON"),
        (lambda text: "[1, 2, 3]", "JSON object"),
        (lambda text: _rehash({**json.loads(text), "format": "something-else"}), "not a calibration record"),
        (lambda text: _rehash({**json.loads(text), "format_version": 4}),
         "format version 4 is not supported \\(this software reads versions 1, 2, 3\\)"),
        (lambda text: _rehash({k: v for k, v in json.loads(text).items() if k != "models"}), "missing field"),
        (lambda text: json.dumps({k: v for k, v in json.loads(text).items() if k != "content_id"}), "missing field"),
        (lambda text: text.replace('"run-2024-001"', '"run-2024-002"'), "content id mismatch"),
        (lambda text: _rehash({**json.loads(text), "models": {"x": {"method": "csf"}}}), "malformed"),
        (lambda text: _rehash({**json.loads(text), "models": {"q": json.loads(text)["models"]["x"]}}),
         "unknown component"),
        (lambda text: _rehash({**json.loads(text), "models": {
            "x": {**json.loads(text)["models"]["x"], "directions": [2]}}}), "malformed"),
    ],
    ids=["truncated", "not-object", "wrong-format", "wrong-version", "missing-models", "missing-id",
         "hash-mismatch", "malformed-model", "unknown-component", "bad-direction"],
)
def test_corrupted_records_raise_one_clear_error(record, corrupt, message):
    with pytest.raises(CalibrationRecordError, match=message) as caught:
        CalibrationRecord.from_json(corrupt(record.to_json()))
    assert "\n" not in str(caught.value)


def test_a_tampered_number_is_caught(record):
    payload = json.loads(record.to_json())
    payload["validity"]["x"][1] += 1e-3
    with pytest.raises(CalibrationRecordError, match="content id mismatch"):
        CalibrationRecord.from_json(json.dumps(payload))
    assert issubclass(CalibrationRecordError, ValueError)


def test_a_named_method_is_evaluated_alone_or_not_at_all(scenario):
    compensators = {"csf": SmoothingSplineCompensator(), "none": NoCompensation()}
    evaluated = calibrate(scenario.data["b"], compensators, method="csf")
    assert {r.method for r in evaluated.evaluation.rows} == {"csf"} and evaluated.method == "csf"
    bare = calibrate(scenario.data["b"], compensators, PROVENANCE, method="csf", evaluation=False)
    again = CalibrationRecord.from_json(bare.to_json(indent=2))
    assert again.evaluation is None and again.method_for("b") == "csf"
    with pytest.raises(ValueError, match="unknown compensator"):
        calibrate(scenario.data["b"], compensators, method="esn")
    with pytest.raises(ValueError, match="needs the evaluation"):
        calibrate(scenario.data["b"], compensators, evaluation=False)


def test_a_record_made_from_partial_data_keeps_validity(scenario):
    data = scenario.data["c"]
    narrow = CalibrationData("c", data.measured, data.reference, data.group, data.point)
    rec = calibrate(narrow, {"csf": SmoothingSplineCompensator()}, method="csf", evaluation=False)
    assert rec.validity["c"] == (float(data.measured.min()), float(data.measured.max()))
