"""The seam between the engine and the measurement core.

The engine only talks to a ``Science`` object: locate + solve a frame triple, the ISO cube, the
ISO statistics, the calibration fit and the compensator in force. ``InstrumentScience`` wires the
real ``instrument`` package (imported lazily, so the engine loads before every piece of the core
exists); tests use a fake with the same methods.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

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
    """What a calibration fit hands back to the engine.

    record_json : the record file's text (written by the engine).
    record_id : the record's identity (what every later run names).
    curves : per component, ``{"measured": [...], "error_before": [...], "error_after": [...],
        "reference": [...], "group": [...]}`` in SI, for the report; ``summary`` free-form figures.
    """

    record_json: str
    record_id: str
    curves: dict[str, dict[str, list]]
    summary: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class Compensator(Protocol):
    record_id: str

    def correct(self, pose: np.ndarray) -> tuple[np.ndarray, list[str]]:
        """Corrected ``(6,)`` pose and flags (e.g. 'x outside calibrated range')."""
        ...


@runtime_checkable
class Science(Protocol):
    def configure(self, station: Any) -> None: ...

    def measure(self, frames: Mapping[str, Any]) -> PoseMeasurement: ...

    def cube_points(self, center: np.ndarray, edge: float) -> tuple[list[str], np.ndarray]: ...

    def visibility_problems(self, opr_in_m: np.ndarray) -> list[str]: ...

    def fit_rigid_transform(self, source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]: ...

    def iso_statistics(self, poses: np.ndarray, commanded: np.ndarray) -> dict[str, Any]: ...

    def fit_calibration(self, kind: str, data: dict[str, list[dict]], provenance: dict) -> CalibrationResult: ...

    def load_compensator(self, path: str | Path) -> Compensator: ...


def record_id_of(text: str) -> str:
    """A content hash, used when a record does not name itself."""
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()[:16]


def _plain(value: Any) -> Any:
    """Any result object (dataclass, namedtuple, numpy) → JSON-able dict/list/float."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if hasattr(value, "_asdict"):
        return {k: _plain(v) for k, v in value._asdict().items()}
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


class InstrumentScience:
    """The real measurement core (``instrument.vision``, ``.pose``, ``.iso9283``, ``.compensation``).

    Every method imports what it needs when first called, and says which piece is missing.
    """

    def __init__(self) -> None:
        self.geometry = None
        self.tool_in_opr = None

    def configure(self, station: Any) -> None:
        from instrument.pose import Geometry  # type: ignore[attr-defined]

        self.geometry = Geometry.from_dict(station.geometry)

    # -- one pose
    def measure(self, frames: Mapping[str, Any]) -> PoseMeasurement:
        from instrument.pose import solve_pose  # type: ignore[attr-defined]
        from instrument.vision import CrossNotFound, locate_cross  # type: ignore[attr-defined]

        crosses, quality = {}, {}
        for screen, frame in frames.items():
            try:
                cross = locate_cross(frame.image, saturation=frame.saturation)
            except (CrossNotFound, ValueError) as exc:
                raise MeasurementFailed(f"screen {screen}: {exc}") from None
            crosses[screen] = cross
            quality[screen] = {
                "center_px": [float(v) for v in cross.center],
                "angle_rad": float(cross.angle),
                "perpendicularity_rad": float(cross.perpendicularity),
                "peak_level": float(cross.peak_level),
                "sections": [int(cross.horizontal.sections), int(cross.vertical.sections)],
                "residual_rms_px": [float(cross.horizontal.residual_rms), float(cross.vertical.residual_rms)],
                "saturated_sections": [
                    int(cross.horizontal.saturated_sections),
                    int(cross.vertical.saturated_sections),
                ],
            }
        try:
            estimate = solve_pose(crosses, self.geometry)
        except (ValueError, ArithmeticError) as exc:
            raise MeasurementFailed(f"pose solver: {exc}") from None
        pose = np.concatenate([np.asarray(estimate.translation, float), np.asarray(estimate.euler, float)])
        return PoseMeasurement(pose=pose, residual_rms=float(estimate.residual_rms), crosses=quality)

    # -- dry run
    def visibility_problems(self, opr_in_m: np.ndarray) -> list[str]:
        """Run the exact forward model (``instrument.pose.predict_measurements``): a cross that
        would leave its camera's image, or a pose the model cannot map, is a problem."""
        from instrument.pose import Pose, PoseError, predict_measurements  # type: ignore[attr-defined]

        try:
            predict_measurements(Pose.from_euler(opr_in_m[:3], opr_in_m[3:]), self.geometry)
        except PoseError as exc:
            return [f"cross not on its screen: {exc}"]
        return []

    # -- ISO 9283
    def cube_points(self, center: np.ndarray, edge: float) -> tuple[list[str], np.ndarray]:
        from instrument.iso9283 import iso_cube_points  # type: ignore[attr-defined]

        cube = iso_cube_points(center, edge)
        return list(cube.order), cube.positions_in_order()

    def fit_rigid_transform(self, source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        from instrument.pose import fit_rigid_transform  # type: ignore[attr-defined]

        result = fit_rigid_transform(source, target)
        if isinstance(result, tuple):
            rotation, translation, *rest = result
            rms = float(rest[0]) if rest else float("nan")
        else:
            rotation, translation = result.rotation, result.translation
            rms = float(getattr(result, "residual_rms", float("nan")))
        return np.asarray(rotation, float), np.asarray(translation, float), rms

    def iso_statistics(self, poses: np.ndarray, commanded: np.ndarray) -> dict[str, Any]:
        from instrument.iso9283 import pose_accuracy, pose_repeatability  # type: ignore[attr-defined]

        confidence = 0.95 if len(poses) >= 3 else None
        out = {k.lower(): v for k, v in _plain(pose_repeatability(poses, confidence=confidence)).items()}
        out.update({k.lower(): v for k, v in _plain(pose_accuracy(poses, commanded, confidence=confidence)).items()})
        return out

    # -- compensation
    def fit_calibration(self, kind: str, data: dict[str, list[dict]], provenance: dict) -> CalibrationResult:
        """``instrument.compensation.calibrate`` over the default compensators (the held-out
        winner per component), on the run's (measured, reference, group, point) rows."""
        from instrument.compensation import CalibrationData, Provenance, calibrate, default_compensators

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
            corrected = np.array([record.correct(component, float(x))[0] for x in d.measured])
            curves[component] = {"measured": d.measured.tolist(), "reference": d.reference.tolist(),
                                 "error_before": (d.measured - d.reference).tolist(),
                                 "error_after": (corrected - d.reference).tolist(), "group": d.group.tolist()}
        summary = {"method": record.method,
                   "evaluation": None if record.evaluation is None else _plain(record.evaluation.to_dict())}
        return CalibrationResult(record_json=record.to_json(indent=1), record_id=record.content_id,
                                 curves=curves, summary=summary)

    def load_compensator(self, path: str | Path) -> Compensator:
        from instrument.compensation import CalibrationRecord  # type: ignore[attr-defined]

        text = Path(path).read_text(encoding="utf-8")
        return _RecordCompensator(CalibrationRecord.from_json(text), text)


class _RecordCompensator:
    def __init__(self, record: Any, text: str) -> None:
        self.record = record
        self.record_id = getattr(record, "content_id", None) or record_id_of(text)

    def correct(self, pose: np.ndarray) -> tuple[np.ndarray, list[str]]:
        import warnings

        with warnings.catch_warnings():  # out-of-range corrections come back as flags
            warnings.simplefilter("ignore")
            values, flags = self.record.correct_pose(dict(zip(COMPONENTS, (float(v) for v in pose))))
        out_of_range = [f"{k} outside the calibrated range" for k, flagged in dict(flags).items() if flagged]
        return np.array([values[k] for k in COMPONENTS], dtype=float), out_of_range
