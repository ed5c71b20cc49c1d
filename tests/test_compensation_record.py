"""CalibrationRecord: round trip, every corruption case, and applying corrections."""

import json
import warnings

import numpy as np
import pytest

from instrument.compensation import (
    FORMAT_VERSION,
    CalibrationRecord,
    CalibrationRecordError,
    CsfPpsoEsnCompensator,
    GaussianProcessCompensator,
    NoCompensation,
    OutOfCalibrationRangeWarning,
    Provenance,
    SmoothingSplineCompensator,
    calibrate,
    paper_like_scenario,
)

PROVENANCE = Provenance(
    run_id="run-2024-001",
    references=({"instrument": "interferometer", "serial": "XL80-0042", "components": ["x"]},
                {"instrument": "rotary table", "serial": "ALIO-7", "components": ["a"]}),
    date="2024-05-02",
    temperature_c=20.4,
)


@pytest.fixture(scope="module")
def scenario():
    return paper_like_scenario(seed=5)


@pytest.fixture(scope="module")
def record(scenario):
    methods = {
        "csf-ppso-esn": CsfPpsoEsnCompensator(n_particles=8, n_iterations=6),
        "csf": SmoothingSplineCompensator(),
        "gaussian_process": GaussianProcessCompensator(),
        "none": NoCompensation(),
    }
    return calibrate({c: scenario.data[c] for c in ("x", "a")}, methods, PROVENANCE)


def test_record_round_trip_keeps_everything(record, scenario):
    text = record.to_json()
    again = CalibrationRecord.from_json(text)
    assert again.to_json() == text and again.content_id == record.content_id
    assert again.provenance == PROVENANCE and again.method == "per-component best"
    assert again.validity == record.validity
    assert again.evaluation.format() == record.evaluation.format()
    probe = np.linspace(0.0, 0.07, 31)
    np.testing.assert_array_equal(again.correct("x", probe)[0], record.correct("x", probe)[0])
    payload = json.loads(text)
    assert payload["format_version"] == FORMAT_VERSION and payload["units"] == {"x": "m", "a": "rad"}
    # the chosen method per component is the evaluation's winner
    for c in ("x", "a"):
        assert record.models[c].method == record.evaluation.best(c)


def test_correction_removes_the_known_error(record, scenario):
    true_value = np.linspace(0.001, 0.069, 40)
    measured = true_value + scenario.true_error["x"](true_value)
    corrected, flags = record.correct("x", measured)
    assert not np.any(flags)
    # group 0's error is the model's frame; the residual is model error only (no noise added here)
    assert np.abs(corrected - true_value).max() < 1.5e-6
    value, flag = record.correct("x", float(measured[3]))
    assert isinstance(value, float) and flag is False


def test_extrapolation_is_flagged_and_warned(record):
    lo, hi = record.validity["a"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, inside = record.correct("a", 0.5 * (lo + hi))
    assert inside is False
    with pytest.warns(OutOfCalibrationRangeWarning, match="outside the calibrated range"):
        _, outside = record.correct("a", hi + 0.01)
    assert outside is True
    with pytest.warns(OutOfCalibrationRangeWarning):
        pose, flags = record.correct_pose({"x": 0.035, "a": lo - 0.001, "c": 0.2})
    assert flags == {"x": False, "a": True, "c": False}
    assert pose["c"] == 0.2 and pose["x"] != 0.035


def test_unknown_components_are_refused(record):
    with pytest.raises(ValueError, match="no model for component 'y'"):
        record.correct("y", 0.01)
    with pytest.raises(ValueError, match="unknown pose component"):
        record.correct_pose({"w": 1.0})


def _rehash(payload):
    """Recompute the content id, so only the intended defect remains."""
    from instrument.compensation._record import _content_id

    payload.pop("content_id", None)
    payload["content_id"] = _content_id(payload)
    return json.dumps(payload)


@pytest.mark.parametrize(
    "corrupt, message",
    [
        (lambda text: text[: len(text) // 2], "not valid JSON"),
        (lambda text: "[1, 2, 3]", "JSON object"),
        (lambda text: _rehash({**json.loads(text), "format": "something-else"}), "not a calibration record"),
        (lambda text: _rehash({**json.loads(text), "format_version": FORMAT_VERSION + 1}), "version"),
        (lambda text: _rehash({k: v for k, v in json.loads(text).items() if k != "models"}), "missing field"),
        (lambda text: json.dumps({k: v for k, v in json.loads(text).items() if k != "content_id"}), "missing field"),
        (lambda text: text.replace('"run-2024-001"', '"run-2024-002"'), "content id mismatch"),
        (lambda text: _rehash({**json.loads(text), "models": {"x": {"method": "csf"}}}), "malformed"),
        (lambda text: _rehash({**json.loads(text), "models": {"q": json.loads(text)["models"]["x"]}}),
         "unknown component"),
    ],
    ids=["truncated", "not-object", "wrong-format", "wrong-version", "missing-models", "missing-id",
         "hash-mismatch", "malformed-model", "unknown-component"],
)
def test_corrupted_records_raise_a_clear_error(record, corrupt, message):
    with pytest.raises(CalibrationRecordError, match=message):
        CalibrationRecord.from_json(corrupt(record.to_json()))


def test_a_tampered_number_is_caught(record):
    payload = json.loads(record.to_json())
    payload["validity"]["x"][1] += 1e-3
    with pytest.raises(CalibrationRecordError, match="content id mismatch"):
        CalibrationRecord.from_json(json.dumps(payload))
    assert issubclass(CalibrationRecordError, ValueError)


def test_fixed_method_record_without_evaluation(scenario):
    rec = calibrate(scenario.data["b"], {"csf": SmoothingSplineCompensator()}, PROVENANCE, method="csf",
                    evaluate_first=False)
    again = CalibrationRecord.from_json(rec.to_json(indent=2))
    assert again.evaluation is None and again.models["b"].method == "csf"
    with pytest.raises(ValueError, match="unknown compensator"):
        calibrate(scenario.data["b"], {"csf": SmoothingSplineCompensator()}, PROVENANCE, method="esn")
