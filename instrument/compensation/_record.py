"""Calibration record: the fitted error models, how they were made, and where they are valid.

Pure: ``to_json()`` gives the text and ``CalibrationRecord.from_json(text)`` checks and loads it;
procedures do the file I/O. The record is self-describing (format name and version, units, method,
provenance, validity per component, the evaluation table) and carries a content id: the SHA-256
of its canonical JSON without the id, so any edit or corruption is detected on load.
"""

from __future__ import annotations

import hashlib
import json
import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from instrument.compensation._compensators import FittedModel
from instrument.compensation._data import COMPONENTS, LINEAR_COMPONENTS
from instrument.compensation._evaluate import EvaluationTable

FORMAT_NAME = "opr-calibration-record"
FORMAT_VERSION = 1


class CalibrationRecordError(ValueError):
    """A calibration record that cannot be trusted: bad JSON, wrong format or version, missing or
    malformed fields, or a content id that does not match the content."""


class OutOfCalibrationRangeWarning(UserWarning):
    """A value was corrected outside the range its error model was calibrated on (extrapolated)."""


@dataclass(frozen=True)
class Provenance:
    """Where a calibration came from.

    Attributes
    ----------
    run_id : the run that recorded the calibration data
    references : reference instruments, e.g. ``[{"instrument": "interferometer", "serial": "XL80-1234",
        "components": ["x", "y", "z"]}]``
    date : ISO 8601 date or date-time of the calibration
    temperature_c : ambient temperature in °C if known
    """

    run_id: str
    references: tuple = ()
    date: str = ""
    temperature_c: float | None = None

    def to_dict(self) -> dict:
        return {"run_id": self.run_id, "references": [dict(r) for r in self.references], "date": self.date,
                "temperature_c": self.temperature_c}

    @classmethod
    def from_dict(cls, d: dict) -> Provenance:
        t = d.get("temperature_c")
        return cls(str(d["run_id"]), tuple(dict(r) for r in d.get("references", [])), str(d.get("date", "")),
                   None if t is None else float(t))


def _canonical(payload: dict) -> str:
    return json.dumps(payload, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _content_id(payload: dict) -> str:
    return "sha256:" + hashlib.sha256(_canonical(payload).encode("utf-8")).hexdigest()


def _finite_json(value):
    """NaN/inf are not JSON: store them as None (the evaluation's empty end-interval cells)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_json(v) for v in value]
    return value


@dataclass(frozen=True)
class CalibrationRecord:
    """Fitted error models per component plus provenance, validity and evaluation.

    Attributes
    ----------
    method : name of the compensation method (or "per-component best")
    models : mapping component → FittedModel (error in SI units against measured value)
    provenance : Provenance
    validity : mapping component → (lo, hi) measured-value range where corrections are trusted
    evaluation : EvaluationTable or None
    """

    method: str
    models: Mapping[str, FittedModel]
    provenance: Provenance
    validity: Mapping[str, tuple] = field(default_factory=dict)
    evaluation: EvaluationTable | None = None

    def __post_init__(self):
        bad = set(self.models) - set(COMPONENTS)
        if bad:
            raise CalibrationRecordError(
                f"calibration record: unknown component(s) {sorted(bad)}; expected {COMPONENTS}"
            )
        validity = {c: tuple(float(v) for v in self.validity.get(c, m.validity)) for c, m in self.models.items()}
        object.__setattr__(self, "validity", validity)
        object.__setattr__(self, "models", dict(self.models))

    # --- serialisation -------------------------------------------------------------------
    def _payload(self) -> dict:
        return _finite_json({
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "units": {c: ("m" if c in LINEAR_COMPONENTS else "rad") for c in self.models},
            "method": self.method,
            "provenance": self.provenance.to_dict(),
            "validity": {c: list(v) for c, v in self.validity.items()},
            "models": {c: m.to_dict() for c, m in self.models.items()},
            "evaluation": None if self.evaluation is None else self.evaluation.to_dict(),
        })

    @property
    def content_id(self) -> str:
        return _content_id(self._payload())

    def to_json(self, indent: int | None = None) -> str:
        payload = self._payload()
        payload["content_id"] = _content_id(payload)
        return json.dumps(payload, sort_keys=True, indent=indent, allow_nan=False)

    @classmethod
    def from_json(cls, text: str) -> CalibrationRecord:
        try:
            payload = json.loads(text)
        except (TypeError, ValueError) as exc:
            raise CalibrationRecordError(f"calibration record is not valid JSON: {exc}") from None
        if not isinstance(payload, dict):
            raise CalibrationRecordError("calibration record: expected a JSON object at the top level")
        if payload.get("format") != FORMAT_NAME:
            raise CalibrationRecordError(
                f"not a calibration record: format is {payload.get('format')!r}, expected {FORMAT_NAME!r}")
        if payload.get("format_version") != FORMAT_VERSION:
            raise CalibrationRecordError(
                f"calibration record format version {payload.get('format_version')!r} is not supported "
                f"(this software reads version {FORMAT_VERSION})")
        missing = [k for k in ("method", "provenance", "validity", "models", "evaluation", "content_id")
                   if k not in payload]
        if missing:
            raise CalibrationRecordError(f"calibration record is missing field(s): {', '.join(missing)}")
        stated = payload.pop("content_id")
        actual = _content_id(payload)
        if stated != actual:
            raise CalibrationRecordError(
                f"calibration record content id mismatch: stated {stated}, content hashes to {actual} "
                "(the file was edited or corrupted)")
        try:
            evaluation = payload["evaluation"]
            if evaluation is not None:
                for row in evaluation["rows"]:
                    for key in ("rms", "max_abs", "end_rms", "noise_floor"):
                        row[key] = float("nan") if row[key] is None else row[key]
                evaluation = EvaluationTable.from_dict(evaluation)
            return cls(
                str(payload["method"]),
                {c: FittedModel.from_dict(m) for c, m in payload["models"].items()},
                Provenance.from_dict(payload["provenance"]),
                {c: (float(v[0]), float(v[1])) for c, v in payload["validity"].items()},
                evaluation,
            )
        except CalibrationRecordError:
            raise
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise CalibrationRecordError(f"calibration record has a malformed field: {exc!r}") from None

    # --- applying -------------------------------------------------------------------------
    def correct(self, component: str, measured):
        """Corrected value(s) = measured − predicted error.

        Returns (corrected, out_of_range): a float and a bool for a scalar input, arrays for an
        array input. Values outside the validity range are still corrected (the curve continues
        linearly) but flagged, with an ``OutOfCalibrationRangeWarning``.
        """
        if component not in self.models:
            raise ValueError(f"calibration record has no model for component {component!r} "
                             f"(it holds {sorted(self.models)})")
        x = np.asarray(measured, dtype=float)
        lo, hi = self.validity[component]
        out = (x < lo) | (x > hi)
        if np.any(out):
            warnings.warn(
                f"component {component}: {int(np.sum(out))} value(s) outside the calibrated range "
                f"[{lo:.6g}, {hi:.6g}]; correction extrapolated", OutOfCalibrationRangeWarning, stacklevel=2)
        corrected = x - self.models[component].predict(x)
        if x.ndim == 0:
            return float(corrected), bool(out)
        return corrected, out

    def correct_pose(self, values: Mapping[str, float]):
        """Correct a pose given as a mapping component → value (any subset of x, y, z, a, b, c).

        Components without a model pass through unchanged (flag False). Returns
        (corrected dict, flags dict component → out_of_range).
        """
        corrected, flags = {}, {}
        for component, value in values.items():
            if component not in COMPONENTS:
                raise ValueError(f"unknown pose component {component!r}; expected one of {COMPONENTS}")
            if component in self.models:
                corrected[component], flags[component] = self.correct(component, float(value))
            else:
                corrected[component], flags[component] = float(value), False
        return corrected, flags


def calibrate(calibration_data, compensators, provenance: Provenance, *, method: str | None = None,
              evaluate_first: bool = True, k: int = 5) -> CalibrationRecord:
    """Evaluate the compensators, fit the chosen one per component on all data, build the record.

    Parameters
    ----------
    calibration_data : CalibrationData, a sequence of them, or a mapping component → data
    compensators : mapping name → Compensator
    method : name of the compensator to use for every component; None keeps, per component, the
        one with the lowest k-fold held-out RMS (method.md §4: keep whichever wins)
    evaluate_first : run ``evaluate`` (needed when ``method`` is None)
    """
    from instrument.compensation._data import as_data_mapping
    from instrument.compensation._evaluate import evaluate

    data = as_data_mapping(calibration_data)
    if method is not None and method not in compensators:
        raise ValueError(f"unknown compensator {method!r}; have {sorted(compensators)}")
    if method is None and not evaluate_first:
        raise ValueError("choosing the best compensator per component needs the evaluation")
    table = evaluate(compensators, data, k=k) if evaluate_first else None
    models = {}
    for component, d in data.items():
        name = method if method is not None else table.best(component)
        models[component] = compensators[name].fit(d.measured, d.error, d.group, d.point)
    return CalibrationRecord(method or "per-component best", models, provenance, evaluation=table)
