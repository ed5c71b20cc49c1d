"""Calibration record: the fitted error models, how they were made, where they are valid, how good.

Pure: ``to_json()`` gives the text and ``CalibrationRecord.from_json(text)`` checks and loads it;
procedures do the file I/O. The record is self-describing (format name and version, units,
method per component, approach directions, provenance, validity per component, the held-out
evaluation and the data it was computed on) and carries a content id: the SHA-256 of its
canonical JSON without the id, so any edit or corruption is detected on load.

Applying it has one convention: ``predict_error`` and ``correct`` both return a
``CorrectionResult`` of arrays shaped like the input, with out-of-range and uncovered-direction
flags; ``correct_pose`` returns a ``PoseCorrection`` of 6-vectors. Nothing is reported through
Python warnings.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from instrument.compensation._compensators import Compensator, FittedModel, default_compensators
from instrument.compensation._data import (
    COMPONENTS,
    LINEAR_COMPONENTS,
    CalibrationData,
    as_data_mapping,
    check_direction,
)
from instrument.compensation._evaluate import EvaluationTable, evaluate
from instrument.compensation._floor import FloorRatio, kept_model_floor_ratios
from instrument.compensation._legacy import upgrade_v1_payload

FORMAT_NAME = "opr-calibration-record"
FORMAT_VERSION = 3
READABLE_VERSIONS = (1, 2, 3)
PER_COMPONENT_BEST = "per-component best"


class CalibrationRecordError(ValueError):
    """A calibration record that cannot be trusted: bad JSON, wrong format or version, missing or
    malformed fields, or a content id that does not match the content."""


@dataclass(frozen=True)
class Provenance:
    """Where a calibration came from (every field optional).

    Attributes
    ----------
    run_id : the run that recorded the calibration data
    references : reference instruments, e.g. ``[{"instrument": "interferometer", "serial": "XL80-1234",
        "components": ["x", "y", "z"]}]``
    date : ISO 8601 date or date-time of the calibration
    temperature_c : ambient temperature in °C if known
    """

    run_id: str = ""
    references: tuple = ()
    date: str = ""
    temperature_c: float | None = None

    def to_dict(self) -> dict:
        return {"run_id": self.run_id, "references": [dict(r) for r in self.references], "date": self.date,
                "temperature_c": self.temperature_c}

    @classmethod
    def from_dict(cls, d: dict) -> Provenance:
        t = d.get("temperature_c")
        return cls(str(d.get("run_id", "")), tuple(dict(r) for r in d.get("references", [])), str(d.get("date", "")),
                   None if t is None else float(t))


def _describe_directions(directions: tuple[int, ...]) -> str:
    if not directions:
        return "recorded no approach direction"
    if len(directions) == 2:
        return "approached from both directions"
    return f"approached from {directions[0]:+d} only"


@dataclass(frozen=True)
class CorrectionResult:
    """What ``CalibrationRecord.predict_error`` and ``.correct`` return (SI units).

    Every array has the shape of the ``measured`` argument (``()`` for a scalar).

    Attributes
    ----------
    component : str
    measured : the values given
    predicted_error : the model's error at each value (for its approach direction)
    corrected : measured − predicted_error
    out_of_range : True where the value lies outside the calibrated range (the correction there
        is the curve's linear continuation: use it knowingly)
    direction_not_covered : True where an approach direction was asked that the calibration did
        not cover (or did not record); the prediction there is the calibrated direction's
    calibrated_range : (lo, hi)
    calibrated_directions : ``()`` not recorded, ``(1,)``, ``(-1,)`` or ``(-1, 1)``
    """

    component: str
    measured: np.ndarray
    predicted_error: np.ndarray
    corrected: np.ndarray
    out_of_range: np.ndarray
    direction_not_covered: np.ndarray
    calibrated_range: tuple[float, float]
    calibrated_directions: tuple[int, ...]

    @property
    def ok(self) -> bool:
        """No value out of range and no uncovered direction."""
        return not (bool(np.any(self.out_of_range)) or bool(np.any(self.direction_not_covered)))

    def messages(self) -> list[str]:
        """One line per kind of problem, for a run log or report (empty when ``ok``)."""
        out = []
        n_out = int(np.sum(self.out_of_range))
        if n_out:
            lo, hi = self.calibrated_range
            out.append(f"{self.component}: {n_out} value(s) outside the calibrated range "
                       f"[{lo:.6g}, {hi:.6g}] (SI); correction extrapolated linearly")
        n_dir = int(np.sum(self.direction_not_covered))
        if n_dir:
            out.append(f"{self.component}: {n_dir} value(s) approached from a direction the calibration did not "
                       f"cover (it {_describe_directions(self.calibrated_directions)}); hysteresis not corrected")
        return out


@dataclass(frozen=True)
class PoseCorrection:
    """What ``CalibrationRecord.correct_pose`` returns: 6-vectors in ``COMPONENTS`` order (x, y, z in
    m; a, b, c in rad).

    Attributes
    ----------
    measured, predicted_error, corrected : (6,) float arrays (predicted_error 0 where not modelled)
    modelled : (6,) bool, the record holds a model for the component
    out_of_range, direction_not_covered : (6,) bool (False where not modelled)
    results : component → CorrectionResult for the modelled components
    """

    measured: np.ndarray
    predicted_error: np.ndarray
    corrected: np.ndarray
    modelled: np.ndarray
    out_of_range: np.ndarray
    direction_not_covered: np.ndarray
    results: dict[str, CorrectionResult]

    @property
    def ok(self) -> bool:
        return all(r.ok for r in self.results.values())

    def messages(self) -> list[str]:
        return [m for r in self.results.values() for m in r.messages()]


def _canonical(payload: dict) -> str:
    return json.dumps(payload, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _content_id(payload: dict) -> str:
    return "sha256:" + hashlib.sha256(_canonical(payload).encode("utf-8")).hexdigest()


def _finite_json(value: Any) -> Any:
    """NaN/inf are not JSON: store them as None (the evaluation's empty end-interval cells)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_json(v) for v in value]
    return value


def _pose_directions(direction: int | Sequence[int | None] | Mapping[str, int | None] | None
                     ) -> dict[str, int | None]:
    if direction is None or isinstance(direction, (int, np.integer)):
        return dict.fromkeys(COMPONENTS, None if direction is None else int(direction))
    if isinstance(direction, Mapping):
        unknown = set(direction) - set(COMPONENTS)
        if unknown:
            raise ValueError(f"unknown pose component(s) {sorted(unknown)}; expected {COMPONENTS}")
        return {c: direction.get(c) for c in COMPONENTS}
    values = list(direction)
    if len(values) != len(COMPONENTS):
        raise ValueError(f"a pose's approach directions need {len(COMPONENTS)} entries, got {len(values)}")
    return dict(zip(COMPONENTS, values))


@dataclass(frozen=True)
class CalibrationRecord:
    """Fitted error models per component plus provenance, validity and evaluation.

    Attributes
    ----------
    method : name of the compensation method used for every component, or "per-component best"
    models : mapping component → FittedModel (error in SI units against measured value)
    provenance : Provenance
    validity : mapping component → (lo, hi) measured-value range where corrections are trusted
    evaluation : EvaluationTable or None
    source_id : the content id stated in the JSON this record was loaded from (None when built
        here); for an older format it differs from ``content_id``, which hashes the current one
    source_version : the format version of that JSON

    ``floor_ratios`` (derived from the evaluation, for records of every version that hold one) says
    per component how close the kept model's held-out RMS is to the noise floor.
    """

    method: str
    models: Mapping[str, FittedModel]
    provenance: Provenance = field(default_factory=Provenance)
    validity: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    evaluation: EvaluationTable | None = None
    source_id: str | None = field(default=None, compare=False)
    source_version: int = field(default=FORMAT_VERSION, compare=False)

    def __post_init__(self) -> None:
        bad = set(self.models) - set(COMPONENTS)
        if bad:
            raise CalibrationRecordError(
                f"calibration record: unknown component(s) {sorted(bad)}; expected {COMPONENTS}")
        validity = {c: (float(self.validity.get(c, m.validity)[0]), float(self.validity.get(c, m.validity)[1]))
                    for c, m in self.models.items()}
        object.__setattr__(self, "validity", validity)
        object.__setattr__(self, "models", dict(self.models))

    # --- what it holds --------------------------------------------------------------------
    @property
    def components(self) -> tuple[str, ...]:
        """Modelled components, in ``COMPONENTS`` order."""
        return tuple(c for c in COMPONENTS if c in self.models)

    def _model(self, component: str) -> FittedModel:
        if component not in self.models:
            raise ValueError(f"calibration record has no model for component {component!r} "
                             f"(it holds {list(self.components)})")
        return self.models[component]

    def method_for(self, component: str) -> str:
        """Name of the compensator whose model corrects ``component``."""
        return self._model(component).method

    def approach_directions(self, component: str) -> tuple[int, ...]:
        """Directions the calibration of ``component`` covered: ``()`` not recorded, ``(1,)``, ``(-1,)``,
        ``(-1, 1)``."""
        return self._model(component).directions

    @property
    def bidirectional(self) -> bool:
        """True when every modelled component was calibrated from both approach directions."""
        return bool(self.models) and all(len(m.directions) == 2 for m in self.models.values())

    @property
    def floor_ratios(self) -> dict[str, FloorRatio]:
        """Component → how close the kept model's held-out RMS is to the noise floor (components
        without an evaluation of their kept method are absent)."""
        return kept_model_floor_ratios(self.models, self.evaluation)

    def floor_messages(self) -> list[str]:
        """One line per component whose kept model is not at the noise floor yet (empty when all are)."""
        return [f.message() for f in self.floor_ratios.values() if not f.at_floor]

    # --- serialisation -------------------------------------------------------------------
    def _payload(self) -> dict:
        return _finite_json({
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "units": {c: ("m" if c in LINEAR_COMPONENTS else "rad") for c in self.models},
            "method": self.method,
            "methods": {c: m.method for c, m in self.models.items()},
            "approach_directions": {c: list(m.directions) for c, m in self.models.items()},
            "provenance": self.provenance.to_dict(),
            "validity": {c: list(v) for c, v in self.validity.items()},
            "models": {c: m.to_dict() for c, m in self.models.items()},
            "evaluation": None if self.evaluation is None else self.evaluation.to_dict(),
            # derived from the evaluation, written for the reader of the file (``floor_ratios``)
            "noise_floor": {c: f.to_dict() for c, f in self.floor_ratios.items()},
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
        """Check and load a record written by this or an earlier format version.

        Raises
        ------
        CalibrationRecordError
            One line naming what is wrong (bad JSON, format, version, missing or malformed
            field, content id mismatch).
        """
        try:
            payload = json.loads(text)
        except (TypeError, ValueError) as exc:
            raise CalibrationRecordError(f"calibration record is not valid JSON: {exc}") from None
        if not isinstance(payload, dict):
            raise CalibrationRecordError("calibration record: expected a JSON object at the top level")
        if payload.get("format") != FORMAT_NAME:
            raise CalibrationRecordError(
                f"not a calibration record: format is {payload.get('format')!r}, expected {FORMAT_NAME!r}")
        version = payload.get("format_version")
        if version not in READABLE_VERSIONS:
            raise CalibrationRecordError(
                f"calibration record format version {version!r} is not supported (this software reads versions "
                f"{', '.join(str(v) for v in READABLE_VERSIONS)})")
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
            if version == 1:
                payload = upgrade_v1_payload(payload)
            evaluation = payload["evaluation"]
            return cls(
                str(payload["method"]),
                {c: FittedModel.from_dict(m) for c, m in payload["models"].items()},
                Provenance.from_dict(payload["provenance"]),
                {c: (float(v[0]), float(v[1])) for c, v in payload["validity"].items()},
                None if evaluation is None else EvaluationTable.from_dict(evaluation),
                source_id=str(stated),
                source_version=int(version),
            )
        except CalibrationRecordError:
            raise
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
            raise CalibrationRecordError(f"calibration record has a malformed field: {exc!r}") from None

    # --- applying -------------------------------------------------------------------------
    def predict_error(self, component: str, measured: np.ndarray | float,
                      direction: np.ndarray | int | None = None) -> CorrectionResult:
        """The model's error at the measured value(s), and the corrected value(s).

        Parameters
        ----------
        component : one of the modelled components
        measured : float or array (SI)
        direction : None (unknown: a bidirectional model predicts mid-way), +1 / −1, or an array
            of them shaped like ``measured``

        Returns
        -------
        CorrectionResult
            Arrays shaped like ``measured``; out-of-range values and directions the calibration
            did not cover are flagged in it (never warned).
        """
        model = self._model(component)
        x = np.asarray(measured, dtype=float)
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{component}: measured values must be finite")
        d = check_direction(direction, f"{component}: correction")
        if d is not None:
            try:
                d = np.broadcast_to(d, x.shape)
            except ValueError:
                raise ValueError(f"{component}: {d.size} approach direction(s) for measured values of shape "
                                 f"{x.shape}; give one direction or one per value") from None
        lo, hi = self.validity[component]
        error = model.predict(x, d)
        covered = model.directions
        not_covered = np.zeros(x.shape, bool) if d is None else ~np.isin(d, covered)
        return CorrectionResult(component, x, error, x - error, (x < lo) | (x > hi), not_covered, (lo, hi), covered)

    def correct(self, component: str, measured: np.ndarray | float,
                direction: np.ndarray | int | None = None) -> CorrectionResult:
        """Corrected value(s) = measured − predicted error: the same ``CorrectionResult`` as
        ``predict_error`` (read ``.corrected``)."""
        return self.predict_error(component, measured, direction)

    def correct_pose(self, pose: Sequence[float] | np.ndarray,
                     direction: int | Sequence[int | None] | Mapping[str, int | None] | None = None
                     ) -> PoseCorrection:
        """Correct one pose (x, y, z, a, b, c), SI units.

        Parameters
        ----------
        pose : 6 values in ``COMPONENTS`` order; components without a model pass through
        direction : None, one ±1 for every component, 6 values (±1 or None) or a mapping
            component → ±1/None

        Returns
        -------
        PoseCorrection
        """
        measured = np.asarray(pose, dtype=float).ravel()
        if measured.size != len(COMPONENTS):
            raise ValueError(f"a pose has {len(COMPONENTS)} components {COMPONENTS}, got {measured.size} values")
        directions = _pose_directions(direction)
        results = {c: self.predict_error(c, measured[i], directions[c])
                   for i, c in enumerate(COMPONENTS) if c in self.models}
        error = np.array([float(results[c].predicted_error) if c in results else 0.0 for c in COMPONENTS])
        flag = lambda attr: np.array([bool(getattr(results[c], attr)) if c in results else False for c in COMPONENTS])
        return PoseCorrection(measured, error, measured - error, np.array([c in results for c in COMPONENTS]),
                              flag("out_of_range"), flag("direction_not_covered"), results)


def calibrate(calibration_data: CalibrationData | Mapping[str, CalibrationData] | Iterable[CalibrationData],
              compensators: Mapping[str, Compensator] | None = None, provenance: Provenance | None = None, *,
              method: str | None = None, seed: int = 0, evaluation: bool = True) -> CalibrationRecord:
    """Evaluate the compensators on held-out data, fit the kept one per component on all data.

    Parameters
    ----------
    calibration_data : CalibrationData, a sequence of them, or a mapping component → data
    compensators : mapping name → Compensator; default ``default_compensators(seed=seed)``
    provenance : default: an empty ``Provenance()``
    method : name of the compensator to use for every component (only it is evaluated); None
        keeps, per component, the one with the lowest leave-one-point-out RMS (method.md §4:
        keep whichever wins)
    seed : seeds the default compensators
    evaluation : False skips the held-out evaluation (then ``method`` is required; the record
        then states no accuracy)

    Returns
    -------
    CalibrationRecord
    """
    data = as_data_mapping(calibration_data)
    compensators = default_compensators(seed=seed) if compensators is None else dict(compensators)
    if method is not None and method not in compensators:
        raise ValueError(f"unknown compensator {method!r}; have {sorted(compensators)}")
    if method is None and not evaluation:
        raise ValueError("choosing the best compensator per component needs the evaluation; name a method "
                         "to calibrate without it")
    scored = compensators if method is None else {method: compensators[method]}
    table = evaluate(scored, data) if evaluation else None
    models = {}
    for component, d in data.items():
        name = method if method is not None else table.best(component) if table is not None else ""
        models[component] = compensators[name].fit(d)
    return CalibrationRecord(method or PER_COMPONENT_BEST, models, provenance or Provenance(), evaluation=table)
