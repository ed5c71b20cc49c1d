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
from instrument.compensation import CalibrationData, CalibrationRecord, Provenance, calibrate, default_compensators
from instrument.iso9283 import pose_accuracy, pose_repeatability
from instrument.pose import Geometry, Pose, PoseError, fit_rigid_transform, predict_measurements, solve_pose
from instrument.vision import CrossMeasurement, CrossNotFound, locate_cross
from procedures._files import read_text_file
from procedures._models import StationFile

COMPONENTS = ("x", "y", "z", "a", "b", "c")  # order of a (6,) pose in M; a, b, c = alpha, theta, gamma
ANGLE_COMPONENT = {"x": "a", "y": "b", "z": "c"}  # rotation about M's axis k


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
        "reference": [...], "group": [...]}`` in SI, for the report; ``summary`` free-form figures.
    """

    record_json: str
    record_id: str
    curves: dict[str, dict[str, list[Any]]]
    summary: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class Compensator(Protocol):
    record_id: str

    def correct(self, pose: np.ndarray) -> tuple[np.ndarray, list[str]]:
        """Corrected ``(6,)`` pose and flags (e.g. 'x outside calibrated range')."""
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
        """A calibration record from per-component rows of measured, reference, group, point."""
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
        winner per component), on the run's (measured, reference, group, point) rows."""
        prepared = {
            component: CalibrationData(component, np.array([r["measured"] for r in rows]),
                                       np.array([r["reference"] for r in rows]),
                                       np.array([r["group"] for r in rows]), np.array([r["point"] for r in rows]))
            for component, rows in data.items()
        }
        record = calibrate(prepared, default_compensators(seed=0),
                           Provenance(run_id=provenance["run_id"], references=tuple(provenance.get("references", ())),
                                      date=provenance.get("date", "")))
        curves = {}
        for component, d in prepared.items():
            corrected = record.correct(component, d.measured).corrected
            curves[component] = {"measured": d.measured.tolist(), "reference": d.reference.tolist(),
                                 "error_before": (d.measured - d.reference).tolist(),
                                 "error_after": (corrected - d.reference).tolist(), "group": d.group.tolist()}
        summary = {"method": record.method,
                   "evaluation": None if record.evaluation is None else _plain(record.evaluation.to_dict())}
        return CalibrationResult(record_json=record.to_json(indent=1), record_id=record.content_id,
                                 curves=curves, summary=summary)

    def load_compensator(self, path: str | Path) -> Compensator:
        text = read_text_file(path, what="calibration record")
        return RecordCompensator(CalibrationRecord.from_json(text))


class RecordCompensator:
    """A calibration record applied to whole poses; each record corrects only its own components."""

    def __init__(self, record: CalibrationRecord) -> None:
        self.record = record
        self.record_id = record.content_id

    def correct(self, pose: np.ndarray) -> tuple[np.ndarray, list[str]]:
        result = self.record.correct_pose(np.asarray(pose, dtype=float))
        return result.corrected, result.messages()
