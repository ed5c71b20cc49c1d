"""The typed blocks of a measured sample, from the measurement core through the step context to the store and back.

A sample is the pose solved from a step's frames (``SolvedPose``, with its ``PoseQuality``), that pose
corrected by the calibration records in force (``CorrectedPose``), what the step read beside it
(``Reference``) and what was commanded (``Commanded``). Each block is a frozen dataclass, SI throughout,
with ``to_stored()`` (the JSON object the store writes, docs/results.md) and ``from_stored()`` (that
object read back, from this version or an earlier one: a key an earlier version did not write is None).

What a sample row holds is kept as it was stored (``Sample.as_stored``): the export gives a run's samples
exactly as they were committed, whichever version committed them.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from instrument import COMPONENTS

Pose = tuple[float, ...]
"""A pose ``[x, y, z, a, b, c]`` in M (m, rad), or a TCP pose ``[x, y, z, rx, ry, rz]`` (m, rotation vector)."""


def as_pose(values: Iterable[Any]) -> Pose:
    """``values`` as a tuple of floats (NaN stays NaN)."""
    return tuple(float(v) for v in values)


def _optional_pose(values: Any) -> Pose | None:
    return None if values is None else as_pose(values)


def _optional_float(value: Any) -> float | None:
    return None if value is None else float(value)


@dataclass(frozen=True)
class FrameExposure:
    """When one frame is known to show the scene (``drivers.camera.Frame``): host wall-clock seconds ``at``,
    meaning ``evidence`` — ``"still since"`` (a still scene since then) or ``"exposure"`` (exposed from then)."""

    camera: str
    at: float
    evidence: str


@dataclass(frozen=True)
class ExposureEvidence:
    """The proof that a pose's frames show the scene after the motion that brought it there ended.

    motion_started, motion_ended : host wall-clock seconds when the last motion before the measurement
        was sent and when it was reported done (None: no motion in this session before it)
    frames : every frame averaged into the pose; each ``still since`` at or after ``motion_started``
        (a scene still since the motion began is its end) or exposed at or after ``motion_ended``
    """

    motion_started: float | None
    motion_ended: float | None
    frames: tuple[FrameExposure, ...]

    def to_stored(self) -> dict[str, Any]:
        return {"motion_started": self.motion_started, "motion_ended": self.motion_ended,
                "frames": [{"camera": f.camera, "at": f.at, "evidence": f.evidence} for f in self.frames]}

    @classmethod
    def from_stored(cls, data: Mapping[str, Any]) -> ExposureEvidence:
        return cls(motion_started=_optional_float(data.get("motion_started")),
                   motion_ended=_optional_float(data.get("motion_ended")),
                   frames=tuple(FrameExposure(str(f["camera"]), float(f["at"]), str(f["evidence"]))
                                for f in data.get("frames") or ()))


@dataclass(frozen=True)
class PoseQuality:
    """How well a pose was measured.

    residual_rms : the solver's consistency residual (m on the screens), the mean over the frames
    pose_std : (6,) the spread of the frames' poses that were averaged (m, rad)
    attempts : how many times the step's frames were grabbed and solved (retries included)
    exposure : the proof that its frames were exposed after the motion ended (None in runs stored before
        frames carried it, and for a move measured in motion)
    """

    residual_rms: float | None = None
    pose_std: Pose | None = None
    attempts: int | None = None
    exposure: ExposureEvidence | None = None


@dataclass(frozen=True)
class SolvedPose:
    """The OPR pose in M as the measurement core solved it from one step's frames, before any correction.

    pose : the mean over the frame triples (m, rad)
    quality : its ``PoseQuality``
    per_frame : each frame triple's pose (None for a move measured in motion: its settled pose is a mean
        of the stream)
    components : the names of the pose's components, in order
    """

    pose: Pose
    quality: PoseQuality = field(default_factory=PoseQuality)
    per_frame: tuple[Pose, ...] | None = None
    components: tuple[str, ...] = COMPONENTS

    def to_stored(self) -> dict[str, Any]:
        stored: dict[str, Any] = {"pose": list(self.pose),
                                  "pose_std": None if self.quality.pose_std is None else list(self.quality.pose_std),
                                  "per_frame": None if self.per_frame is None else [list(p) for p in self.per_frame],
                                  "residual_rms": self.quality.residual_rms, "components": list(self.components),
                                  "attempts": self.quality.attempts}
        if self.quality.exposure is not None:
            stored["exposure"] = self.quality.exposure.to_stored()
        return stored

    @classmethod
    def from_stored(cls, data: Mapping[str, Any]) -> SolvedPose:
        per_frame = data.get("per_frame")
        attempts = data.get("attempts")
        exposure = data.get("exposure")
        return cls(pose=as_pose(data.get("pose") or ()),
                   quality=PoseQuality(residual_rms=_optional_float(data.get("residual_rms")),
                                       pose_std=_optional_pose(data.get("pose_std")),
                                       attempts=None if attempts is None else int(attempts),
                                       exposure=None if exposure is None else ExposureEvidence.from_stored(exposure)),
                   per_frame=None if per_frame is None else tuple(as_pose(p) for p in per_frame),
                   components=tuple(data.get("components") or COMPONENTS))


@dataclass(frozen=True)
class CorrectedPose:
    """The solved pose corrected with the calibration records in force.

    pose : the corrected pose in M (m, rad)
    records : the ids of the records applied, in order
    flags : what the records said of the correction (a value beyond a record's range ...)
    direction : per component the approach direction the correction was chosen for (±1, None: unknown)
    """

    pose: Pose
    records: tuple[str, ...] = ()
    flags: tuple[str, ...] = ()
    direction: Mapping[str, int | None] | None = None

    def to_stored(self) -> dict[str, Any]:
        return {"pose": list(self.pose), "flags": list(self.flags), "records": list(self.records),
                "direction": None if self.direction is None else dict(self.direction)}

    @classmethod
    def from_stored(cls, data: Mapping[str, Any]) -> CorrectedPose:
        return cls(pose=as_pose(data.get("pose") or ()), records=tuple(data.get("records") or ()),
                   flags=tuple(str(f) for f in data.get("flags") or ()), direction=data.get("direction"))


_REFERENCE_FIELDS = ("value", "robot_tcp_pose", "approach", "environment")
_NOT_A_READING = ("session",)  # earlier versions kept a session's test conditions here (now a run-level record)


@dataclass(frozen=True)
class Reference:
    """What a step read beside the pose (SI, JSON-able), as its kind recorded it.

    value : the reference the calibration compares the measured component against (m or rad), else None
    robot_tcp_pose : the TCP pose the robot reported, base frame (m, rotation vector)
    approach : the direction the pose was approached from: per component ±1 or None (an ISO point), or
        the calibration line's direction ±1
    environment : the environmental unit's reading at the step (docs/results.md), or None
    readings : what else the kind read (the interferometer's raw and compensated readings, the table's
        angle, the datum, a streamed move's summary and figures ...), by name
    """

    value: float | None = None
    robot_tcp_pose: Pose | None = None
    approach: Mapping[str, int | None] | int | None = None
    environment: Mapping[str, Any] | None = None
    readings: Mapping[str, Any] = field(default_factory=dict)

    def to_stored(self) -> dict[str, Any]:
        return {"value": self.value, "robot_tcp_pose": None if self.robot_tcp_pose is None
                else list(self.robot_tcp_pose), "approach": self.approach, "environment": self.environment,
                **self.readings}

    @classmethod
    def from_stored(cls, data: Mapping[str, Any] | None) -> Reference:
        if not data:
            return cls()
        approach = data.get("approach")
        return cls(value=_optional_float(data.get("value")), robot_tcp_pose=_optional_pose(data.get("robot_tcp_pose")),
                   approach=approach if approach is None or isinstance(approach, Mapping) else int(approach),
                   environment=data.get("environment"),
                   readings={k: v for k, v in data.items() if k not in _REFERENCE_FIELDS + _NOT_A_READING})


@dataclass(frozen=True)
class Commanded:
    """Where the devices were sent for a step: the robot's TCP pose (base frame), the table's angle (rad), and
    the nominal value of the calibrated component (m or rad) where the step has one."""

    tcp_pose: Pose | None = None
    table_angle: float | None = None
    nominal: float | None = None

    def to_stored(self) -> dict[str, Any]:
        return {"tcp_pose": None if self.tcp_pose is None else list(self.tcp_pose), "table_angle": self.table_angle,
                "nominal": self.nominal}

    @classmethod
    def from_stored(cls, data: Mapping[str, Any] | None) -> Commanded:
        data = data or {}
        return cls(tcp_pose=_optional_pose(data.get("tcp_pose")), table_angle=_optional_float(data.get("table_angle")),
                   nominal=_optional_float(data.get("nominal")))


SAMPLE_FIELDS = ("run_id", "step_index", "step_key", "phase", "label", "ok", "error", "commanded", "solved",
                 "corrected", "crosses", "reference", "meta", "frames", "t_start", "t_measured", "t_committed")
"""A sample row's columns, in the store's order (and the export's)."""


@dataclass(frozen=True)
class Sample:
    """One measured (or failed) step of a run, as committed.

    ``solved``, ``corrected`` and ``reference`` are the typed blocks above; ``crosses`` is what the core
    said of each located cross (per screen, per frame triple); ``meta`` the step's plan data (axis, cycle,
    nominal value ...); ``frames`` the saved frame files, relative to the run's folder.
    """

    run_id: str
    step_index: int
    step_key: str
    phase: str
    label: str | None = None
    ok: bool = True
    error: str | None = None
    commanded: Commanded = field(default_factory=Commanded)
    solved: SolvedPose | None = None
    corrected: CorrectedPose | None = None
    crosses: Mapping[str, Any] | None = None
    reference: Reference = field(default_factory=Reference)
    meta: Mapping[str, Any] = field(default_factory=dict)
    frames: tuple[str, ...] = ()
    t_start: float | None = None
    t_measured: float | None = None
    t_committed: float | None = None
    stored: Mapping[str, Any] | None = field(default=None, compare=False, repr=False)
    """The row as it was read from the store (JSON columns decoded), kept for ``as_stored``."""

    @property
    def pose(self) -> Pose | None:
        """The best pose of the step: corrected when a record was applied, else as solved (None: failed)."""
        best = self.corrected or self.solved
        return None if best is None else best.pose

    @property
    def quality(self) -> PoseQuality | None:
        return None if self.solved is None else self.solved.quality

    def measured_pose(self) -> Pose:
        """``pose`` of a sample that has one (a measured one); a ``ValueError`` naming the step otherwise."""
        if self.pose is None:
            raise ValueError(f"{self.step_key}: the sample has no measured pose")
        return self.pose

    def robot_target(self) -> Pose:
        """The TCP pose the robot was sent to; a ``ValueError`` naming the step when it was sent none."""
        if self.commanded.tcp_pose is None:
            raise ValueError(f"{self.step_key}: the step commanded no robot pose")
        return self.commanded.tcp_pose

    def as_stored(self) -> dict[str, Any]:
        """The sample row as the store holds it: the row read back, or the one ``to_row`` writes."""
        return dict(self.stored) if self.stored is not None else self.to_row()

    def to_row(self) -> dict[str, Any]:
        """The JSON-able row the store writes for this sample (``SAMPLE_FIELDS``)."""
        return {"run_id": self.run_id, "step_index": self.step_index, "step_key": self.step_key, "phase": self.phase,
                "label": self.label, "ok": self.ok, "error": self.error, "commanded": self.commanded.to_stored(),
                "solved": None if self.solved is None else self.solved.to_stored(),
                "corrected": None if self.corrected is None else self.corrected.to_stored(),
                "crosses": None if self.crosses is None else dict(self.crosses),
                "reference": self.reference.to_stored(), "meta": dict(self.meta),
                "frames": list(self.frames) or None, "t_start": self.t_start, "t_measured": self.t_measured,
                "t_committed": self.t_committed}

    @classmethod
    def from_row(cls, row: Mapping[str, Any]) -> Sample:
        """A row read back (JSON columns decoded), from this version or an earlier one."""
        return cls(run_id=row["run_id"], step_index=int(row["step_index"]), step_key=row["step_key"],
                   phase=row["phase"], label=row["label"], ok=bool(row["ok"]), error=row["error"],
                   commanded=Commanded.from_stored(row["commanded"]),
                   solved=None if row["solved"] is None else SolvedPose.from_stored(row["solved"]),
                   corrected=None if row["corrected"] is None else CorrectedPose.from_stored(row["corrected"]),
                   crosses=row["crosses"], reference=Reference.from_stored(row["reference"]),
                   meta=row["meta"] or {}, frames=tuple(row["frames"] or ()), t_start=row["t_start"],
                   t_measured=row["t_measured"], t_committed=row["t_committed"], stored=dict(row))
