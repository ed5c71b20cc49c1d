"""The seam between the engine and the measurement core.

The engine and the procedure kinds talk to a ``Science`` object: locate + solve a frame triple,
the dry run's visibility check, the rigid fit, the ISO statistics, the calibration fit and the
compensator in force. ``InstrumentScience`` wires the real ``instrument`` package; tests use a
fake with the same methods.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from drivers.camera import Frame
from instrument.compensation import (
    LOGO,
    LOPO,
    CalibrationData,
    CalibrationRecord,
    Provenance,
    calibrate,
    default_compensators,
)
from instrument.iso9283 import pose_accuracy, pose_repeatability
from instrument.pose import Geometry, Pose, PoseError, fit_rigid_transform, predict_measurements, solve_pose
from instrument.vision import CrossMeasurement, CrossNotFound, locate_cross
from procedures.station._files import read_text_file
from procedures.station._models import StationFile


class MeasurementFailed(ValueError):
    """A frame triple gave no pose (no cross, a partial cross, a solver that did not converge)."""


@dataclass
class PoseMeasurement:
    """The OPR pose in M from one frame triple.

    pose : (6,) ``[x, y, z, alpha, theta, gamma]``, metres and radians.
    residual_rms : float, the solver's consistency residual (metres on the screens).
    crosses : per screen, the located cross's quality figures (JSON-able).
    """

    pose: np.ndarray
    residual_rms: float
    crosses: dict[str, dict[str, Any]] = field(default_factory=dict)


@dataclass
class CalibrationResult:
    """What a calibration fit hands back.

    record_json : the record file's text (written by the calibration kind).
    record_id : the record's identity (what every later run names).
    curves : per component, ``{"measured": [...], "error_before": [...], "error_after": [...],
        "error_after_held_out": [...], "reference": [...], "group": [...], "direction": [...]}`` in SI,
        one entry per row given (``error_after`` in-sample; ``error_after_held_out`` the kept method's
        leave-one-point-out residual, None at the end points, which are never held out);
    summary : ``{"method", "methods": {component: name}, "evaluation": EvaluationTable.to_dict()}``.
    """

    record_json: str
    record_id: str
    curves: dict[str, dict[str, list[Any]]]
    summary: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class Compensator(Protocol):
    record_id: str

    def correct(self, pose: np.ndarray, direction: Mapping[str, int | None] | None = None
                ) -> tuple[np.ndarray, list[str]]:
        """Corrected ``(6,)`` pose and flags (e.g. 'x outside calibrated range'); ``direction``: the
        approach direction (±1, None: unknown) per component, for a record that models hysteresis."""
        ...

    def info(self) -> dict[str, Any]:
        """What the record says about itself, JSON-able (SI): ``id``, ``path``, ``components``,
        ``methods``, ``validity``, ``approach_directions``, ``bidirectional``, ``date``, ``run_id``,
        ``references``, ``temperature_c`` and ``evaluation`` (component → held-out figures of the
        method in force; see ``record_info``)."""
        ...


@runtime_checkable
class Science(Protocol):
    def configure(self, station: StationFile) -> None:
        """Take the station's geometry (called before a run's first pose)."""
        ...

    def measure(self, frames: Mapping[str, Frame]) -> PoseMeasurement:
        """One frame per screen → the OPR pose; raises ``MeasurementFailed``."""
        ...

    def visibility_problems(self, opr_in_m: np.ndarray) -> list[str]:
        """Why the crosses of the OPR at ``opr_in_m`` (6,) would not all be seen (empty: they would)."""
        ...

    def fit_rigid_transform(self, source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """``target ≈ R·source + t``: (R (3, 3), t (3,), residual RMS)."""
        ...

    def iso_statistics(self, poses: np.ndarray, commanded: np.ndarray) -> dict[str, Any]:
        """ISO 9283 RP and AP of ``poses`` (n, 6) against ``commanded`` (6,), JSON-able, lower-case keys."""
        ...

    def fit_calibration(self, kind: str, data: dict[str, list[dict[str, Any]]],
                        provenance: dict[str, Any]) -> CalibrationResult:
        """A calibration record from per-component rows of measured, reference, group, point and,
        optionally, direction (±1, the approach direction)."""
        ...

    def load_compensator(self, path: str | Path) -> Compensator:
        """The compensator of a calibration record file."""
        ...


def _plain(value: Any) -> Any:
    """A result object of the core (dataclass, numpy) → JSON-able dict/list/float."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


def _cross_quality(cross: CrossMeasurement) -> dict[str, Any]:
    return {
        "center_px": [float(v) for v in cross.center],
        "angle_rad": float(cross.angle),
        "perpendicularity_rad": float(cross.perpendicularity),
        "peak_level": float(cross.peak_level),
        "sections": [int(cross.horizontal.sections), int(cross.vertical.sections)],
        "residual_rms_px": [float(cross.horizontal.residual_rms), float(cross.vertical.residual_rms)],
        "saturated_sections": [int(cross.horizontal.saturated_sections), int(cross.vertical.saturated_sections)],
    }


class InstrumentScience:
    """The real measurement core (``instrument.vision``, ``.pose``, ``.iso9283``, ``.compensation``)."""

    def __init__(self) -> None:
        self._geometry: Geometry | None = None

    @property
    def geometry(self) -> Geometry:
        if self._geometry is None:
            raise RuntimeError("InstrumentScience.configure(station) must come before any measurement")
        return self._geometry

    def configure(self, station: StationFile) -> None:
        self._geometry = Geometry.from_dict(station.geometry)

    # -- one pose
    def measure(self, frames: Mapping[str, Frame]) -> PoseMeasurement:
        crosses: dict[str, CrossMeasurement] = {}
        for screen, frame in frames.items():
            try:
                crosses[screen] = locate_cross(frame.image, saturation=frame.saturation)
            except (CrossNotFound, ValueError) as exc:
                raise MeasurementFailed(f"screen {screen}: {exc}") from None
        try:
            estimate = solve_pose(crosses, self.geometry)
        except (ValueError, ArithmeticError) as exc:
            raise MeasurementFailed(f"pose solver: {exc}") from None
        pose = np.concatenate([np.asarray(estimate.translation, float), np.asarray(estimate.euler, float)])
        return PoseMeasurement(pose=pose, residual_rms=float(estimate.residual_rms),
                               crosses={screen: _cross_quality(cross) for screen, cross in crosses.items()})

    # -- dry run
    def visibility_problems(self, opr_in_m: np.ndarray) -> list[str]:
        """Run the exact forward model (``instrument.pose.predict_measurements``): a cross that
        would leave its camera's image, or a pose the model cannot map, is a problem."""
        try:
            predict_measurements(Pose.from_euler(opr_in_m[:3], opr_in_m[3:]), self.geometry)
        except PoseError as exc:
            return [f"cross not on its screen: {exc}"]
        return []

    # -- ISO 9283
    def fit_rigid_transform(self, source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        fit = fit_rigid_transform(source, target)
        return np.asarray(fit.rotation, float), np.asarray(fit.translation, float), float(fit.residual_rms)

    def iso_statistics(self, poses: np.ndarray, commanded: np.ndarray) -> dict[str, Any]:
        confidence = 0.95 if len(poses) >= 3 else None
        out = {k.lower(): v for k, v in _plain(pose_repeatability(poses, confidence=confidence)).items()}
        out.update({k.lower(): v for k, v in _plain(pose_accuracy(poses, commanded, confidence=confidence)).items()})
        return out

    # -- compensation
    def fit_calibration(self, kind: str, data: dict[str, list[dict[str, Any]]],
                        provenance: dict[str, Any]) -> CalibrationResult:
        """``instrument.compensation.calibrate`` over the default compensators (the held-out
        winner per component), on the run's (measured, reference, group, point, direction) rows;
        then the kept method's leave-one-point-out residual of every interior observation."""
        prepared = {component: _calibration_data(component, rows) for component, rows in data.items()}
        record = calibrate(prepared, default_compensators(seed=0),
                           Provenance(run_id=provenance["run_id"], references=tuple(provenance.get("references", ())),
                                      date=provenance.get("date", ""), temperature_c=provenance.get("temperature_c")))
        curves = {}
        for component, d in prepared.items():
            corrected = record.correct(component, d.measured, d.direction).corrected
            curves[component] = {"measured": d.measured.tolist(), "reference": d.reference.tolist(),
                                 "error_before": (d.measured - d.reference).tolist(),
                                 "error_after": (corrected - d.reference).tolist(), "group": d.group.tolist(),
                                 "direction": None if d.direction is None else d.direction.tolist(),
                                 "error_after_held_out": _held_out(record.method_for(component), d)}
        summary = {"method": record.method, "methods": {c: record.method_for(c) for c in record.components},
                   "evaluation": None if record.evaluation is None else _plain(record.evaluation.to_dict())}
        return CalibrationResult(record_json=record.to_json(indent=1), record_id=record.content_id,
                                 curves=curves, summary=summary)

    def load_compensator(self, path: str | Path) -> Compensator:
        text = read_text_file(path, what="calibration record")
        return RecordCompensator(CalibrationRecord.from_json(text), path=str(path))


def _calibration_data(component: str, rows: list[dict[str, Any]]) -> CalibrationData:
    directions = [r.get("direction") for r in rows]
    direction = np.array(directions) if all(d in (1, -1) for d in directions) else None
    return CalibrationData(component, np.array([r["measured"] for r in rows]), np.array([r["reference"] for r in rows]),
                           np.array([r["group"] for r in rows]), np.array([r["point"] for r in rows]), direction)


def _held_out(method: str, data: CalibrationData) -> list[float | None]:
    """The kept method's leave-one-point-out residual of each observation, in the rows' order.

    As ``instrument.compensation``'s own leave-one-point-out evaluation: each interior point in turn
    is left out (all its repeats, groups and directions), the method refitted on the rest predicts
    it with its group's offset from that fit. None at the two end points, which are never held out.
    """
    compensator = default_compensators(seed=0)[method]
    out: list[float | None] = [None] * data.measured.size
    direction = data.direction
    for held in data.point_order()[1:-1]:
        test = data.point == held
        model = compensator.fit(data.subset(~test))
        offsets = np.array([model.group_offset(g) for g in data.group[test]])
        predicted = model.predict(data.measured[test], None if direction is None else direction[test])
        for index, residual in zip(np.flatnonzero(test), data.error[test] + offsets - predicted):
            out[int(index)] = float(residual)
    return out


def record_info(record: CalibrationRecord, path: str | None = None) -> dict[str, Any]:
    """A calibration record's identity, validity, directions and held-out figures, JSON-able (SI).

    ``evaluation[c]``: ``method``, ``heldout_rms``/``heldout_max`` (leave-one-point-out, the method in
    force), ``group_heldout_rms`` (leave-one-group-out), ``uncompensated_rms`` (the ``none`` method's
    leave-one-point-out RMS: the raw error), ``noise_floor``, ``n_heldout``, ``n_points``,
    ``n_observations``, ``n_groups``, ``directions``; empty for a record without an evaluation.
    """
    evaluation: dict[str, dict[str, Any]] = {}
    table = record.evaluation
    for c in record.components:
        if table is None:
            continue
        method = record.method_for(c)
        rows = {(r.method, r.scheme): r for r in table.select(component=c)}
        kept = rows.get((method, LOPO))
        if kept is None:
            continue
        group = rows.get((method, LOGO))
        raw = rows.get(("none", LOPO))
        data = table.data.get(c, {})
        evaluation[c] = {
            "method": method, "heldout_rms": kept.rms, "heldout_max": kept.max_abs, "noise_floor": kept.noise_floor,
            "n_heldout": kept.n_heldout, "group_heldout_rms": None if group is None else group.rms,
            "uncompensated_rms": None if raw is None else raw.rms,
            "n_points": data.get("n_points"), "n_observations": data.get("n_observations"),
            "n_groups": data.get("n_groups"), "directions": data.get("directions"),
        }
    provenance = record.provenance
    return _plain({
        "id": record.content_id, "source_id": record.source_id, "path": path, "components": list(record.components),
        "methods": {c: record.method_for(c) for c in record.components},
        "validity": {c: list(v) for c, v in record.validity.items()},
        "approach_directions": {c: list(record.approach_directions(c)) for c in record.components},
        "bidirectional": record.bidirectional, "date": provenance.date, "run_id": provenance.run_id,
        "references": [dict(r) for r in provenance.references], "temperature_c": provenance.temperature_c,
        "evaluation": evaluation,
    })


class RecordCompensator:
    """A calibration record applied to whole poses; each record corrects only its own components."""

    def __init__(self, record: CalibrationRecord, path: str | None = None) -> None:
        self.record = record
        self.record_id = record.content_id
        self.path = path

    def correct(self, pose: np.ndarray, direction: Mapping[str, int | None] | None = None
                ) -> tuple[np.ndarray, list[str]]:
        result = self.record.correct_pose(np.asarray(pose, dtype=float), direction=direction)
        return result.corrected, result.messages()

    def info(self) -> dict[str, Any]:
        return record_info(self.record, self.path)
