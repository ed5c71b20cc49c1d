"""The ``ProcedureKind`` Protocol the engine drives, and the small types that cross it.

A kind plans a run as a fixed list of ``Step``s, brings the OPR to each step's pose (``move``),
reads what the step measures (``measure``: its references and the pose from the frames, through
a ``StepContext``), and turns the committed samples into results (``analyse``, through a narrow
``AnalysisContext``). The engine knows no kind by name; ``procedures.kinds`` registers them.

A kind shows nothing itself: it declares what the report and the faces need to show its runs — a
title from the parameters in force (``title``), the shape of its results (``result_shape``, by which
``procedures.report`` finds the sections that show them), whether its runs are judged against ISO
9283's test conditions (``iso_test_conditions``) and which figures a robot's history follows
(``history_figures``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Protocol, TypeVar

from drivers.interferometer import Interferometer
from drivers.robot import Robot
from drivers.rotary_table import RotaryTable
from procedures.kinds._parameters import MotionParameters, ProcedureBase
from procedures.kinds._setups import Setup
from procedures.station import StationFile
from procedures.store import CorrectedPose, Pose, Reference, Sample, SessionConditions, SolvedPose

if TYPE_CHECKING:  # the measurement core loads with the engine that measures, not with the kinds' models
    from procedures.station import Compensator, Science, TruthLog

S = TypeVar("S")
DeviceRole = Literal["robot", "rotary_table", "interferometer"]  # the cameras serve every kind
RESULTS_VERSION = 2  # the layout of the results the kinds write (docs/results.md); results stored before it have none


class ResultShape(StrEnum):
    """The shapes of results the built-in kinds write (docs/results.md); the report keys its sections on them.

    A kind of a new family may declare a shape of its own (any string) and register a section for it
    (``procedures.report.register_section``).
    """

    ISO_POSE = "iso_pose"  # figures per point of the ISO cube, test conditions, deviations
    CALIBRATION = "calibration"  # a calibration record, its held-out evaluation and residuals per component
    STABILISATION = "stabilisation"  # stabilisation time and overshoot per point and speed
    PATH = "path"  # path accuracy, repeatability, cornering and velocity per speed


@dataclass(frozen=True)
class Step:
    """One measured pose of a plan.

    Attributes
    ----------
    index : int
        Position in the plan (0-based); the sample's key in the store.
    key : str
        Readable identity, e.g. ``"disp/x/g1/r0/p03"``.
    phase : str
        What the sample is for, e.g. ``"calibration"``, ``"transform"``, ``"iso"``.
    setup : Setup
        What must be true of the cell (e.g. ``OprOnTable("x")``).
    tcp_pose : (6,) list or None
        Commanded UR TCP pose in the base frame (metres, rotation vector); the dry run checks it.
    table_angle : float or None
        Commanded table angle, rad.
    label : str
        Point name (``"P1"``) or calibration point.
    meta : dict
        Axis, group, repeat, cycle, nominal value (SI) ..., stored with the sample.
    via : tuple of (6,) lists
        Robot poses the move may pass through first (an approach's pre-position); the dry run
        checks them against the envelope too.
    """

    index: int
    key: str
    phase: str
    setup: Setup
    tcp_pose: list[float] | None = None
    table_angle: float | None = None
    label: str = ""
    meta: dict[str, Any] = field(default_factory=dict)
    via: tuple[list[float], ...] = ()

    def robot_target(self) -> list[float]:
        """The commanded TCP pose of a step that moves the robot (a plan without one is a bug)."""
        if self.tcp_pose is None:
            raise ValueError(f"step {self.key}: the plan gives no robot pose")
        return self.tcp_pose

    def table_target(self) -> float:
        """The commanded table angle of a step that turns the table (a plan without one is a bug)."""
        if self.table_angle is None:
            raise ValueError(f"step {self.key}: the plan gives no table angle")
        return self.table_angle


@dataclass(frozen=True)
class PoseReading:
    """The OPR pose from one step's camera frames, or why there is none (``ok`` False, ``error``).

    ``solved``: the pose as solved, with its quality; ``corrected``: after the calibration records in
    force; ``crosses``: what the core said of each located cross; ``frames``: saved frame files, relative
    to the run folder; ``attempts``: how many times the frames were grabbed and solved.
    """

    ok: bool
    solved: SolvedPose | None = None
    corrected: CorrectedPose | None = None
    crosses: dict[str, Any] | None = None
    frames: list[str] | None = None
    t_measured: float | None = None
    attempts: int = 0
    error: str | None = None

    @property
    def pose(self) -> Pose | None:
        """The best pose: corrected if a record was applied, else solved."""
        best = self.corrected or self.solved
        return None if best is None else best.pose


@dataclass(frozen=True)
class Reading:
    """What one step measured: the pose, and the references the kind read beside it (SI).

    ``reference.value``, when present, is the reference the calibration compares against.
    ``stream``: the move's pose stream (``StreamRecord``) of a kind that measures in motion; ``session``:
    the test conditions this session started under, handed back with the session's first reading. The
    engine stores both with the sample, in the same transaction.
    """

    pose: PoseReading
    reference: Reference = field(default_factory=Reference)
    stream: Any = None
    session: SessionConditions | None = None


class StepContext(Protocol):
    """What a kind's ``move`` and ``measure`` may use: the devices, motion at the run's speed,
    the settle wait, the frames → pose measurement (retries, saved frames, compensation), and the
    kind's memory for this session of the run (``session_state``).
    """

    def session_state(self, state: type[S]) -> S:
        """The kind's memory for this session of the run (one ``execute()``): an instance of ``state``, a class
        the kind (or a helper it calls) declares, made with no arguments at the session's first call and the
        same object at every later one. A session starts empty (a run and each resume), so whatever a kind
        keeps there (an interferometer datum, say) is known to be valid only for steps measured by this
        process since then."""
        ...

    def wait(self, seconds: float) -> None:
        """Sleep (an abort cuts it short)."""
        ...

    def log(self, kind: str, message: str) -> None:
        """An event in the run's log (``instrument show``, the report)."""
        ...

    @property
    def station(self) -> StationFile:
        """The station file the run uses (frames, envelope, which devices it has)."""
        ...

    @property
    def robot(self) -> Robot: ...

    @property
    def table(self) -> RotaryTable: ...

    @property
    def interferometer(self) -> Interferometer: ...

    def move_robot(self, tcp_pose: Sequence[float]) -> None:
        """Linear move at the procedure's speed and acceleration, within its move timeout."""
        ...

    def turn_table(self, angle: float, speed: float) -> None:
        """Turn the table to ``angle`` (rad) at ``speed`` (rad/s) and wait until it is in position."""
        ...

    def settle(self) -> None:
        """Wait the procedure's settle time (an abort cuts it short)."""
        ...

    def stream_motion(self, step: Step, motion: Callable[[], None], *, rate_hz: float, exposure_s: float,
                      hold_s: float, target_in_m: Sequence[float] | None = None,
                      direction: Mapping[str, int | None] | None = None) -> Any:
        """Stream the cameras while ``motion()`` runs and ``hold_s`` after; → the move's
        ``_dynamic_stream.StreamRecord`` (poses corrected for ``direction``, times on the controller's clock)."""
        ...

    def measure_pose(self, step: Step, *, direction: Mapping[str, int | None] | None = None,
                     expected: Mapping[int, float] | None = None) -> PoseReading:
        """Grab ``frames_per_pose`` frame triples and solve the pose, retrying failed frames; correct it
        with the records in force, for the approach ``direction`` per component (±1; None: unknown).
        ``expected``: pose component index (0–2 position, 3–5 angle) → the raw value the pose should have
        where the devices were sent (nominal frames, SI); a solved pose farther than the parameters'
        ``plausibility_mm`` / ``plausibility_deg`` from it is a failed attempt (a stale or wrong frame)."""
        ...


@dataclass(frozen=True)
class AnalysisContext:
    """What a kind's ``analyse`` may use: no devices, no engine."""

    run_id: str
    station: StationFile
    science: Science
    compensators: Sequence[Compensator]
    run_dir: Path
    truth: TruthLog | None = None
    streams: Callable[[Sequence[int] | None], dict[int, Any]] | None = None
    """The run's stored pose streams by step (``RunStore.streams``), of the given steps or all."""
    sessions: Sequence[SessionConditions] = ()
    """The test conditions of each session of the run, oldest first (``RunStore.sessions``)."""
    progress: Callable[[str, int, int], None] | None = None
    """``progress(stage, k, n)``: how far a long analysis is (``"uncertainty", 3, 9``), for the faces' progress."""


@dataclass(frozen=True)
class Analysis:
    """A finished run's results (JSON-able, SI) and the calibration record it wrote, if any."""

    results: dict[str, Any]
    calibration_record_id: str | None = None


P = TypeVar("P", bound=MotionParameters)


class ProcedureKind(Protocol[P]):
    """One kind of procedure (``procedure:`` in the YAML). Stateless: the parameters come in."""

    @property
    def name(self) -> str:
        """The YAML's ``procedure:`` value and the schema's file name."""
        ...

    @property
    def parameters(self) -> type[P]:
        """The pydantic model of the YAML's ``parameters``."""
        ...

    @property
    def file_model(self) -> type[ProcedureBase]:
        """The pydantic model of the whole procedure file (its JSON Schema is the kind's schema)."""
        ...

    def plan(self, params: P, station: StationFile) -> list[Step]:
        """The run's steps: a pure function of the parameters and the station, so a resumed run
        rebuilds exactly the same list."""
        ...

    def devices(self, params: P) -> tuple[DeviceRole, ...]:
        """The devices besides the cameras that the dry run must find reachable and healthy."""
        ...

    def applies_compensation(self, params: P) -> bool:
        """Whether measured poses are corrected with the station's calibration records."""
        ...

    def move(self, step: Step, params: P, ctx: StepContext) -> None:
        """Bring the OPR to the step's pose (before a set-up that needs it in place)."""
        ...

    def measure(self, step: Step, params: P, ctx: StepContext) -> Reading:
        """Settle, read the references, measure the pose."""
        ...

    def analyse(self, samples: Sequence[Sample], params: P, ctx: AnalysisContext) -> Analysis:
        """The run's results from its committed samples (failed ones included, ``ok`` False)."""
        ...

    @property
    def result_shape(self) -> str:
        """The shape of the results ``analyse`` writes (a ``ResultShape`` for the built-in kinds)."""
        ...

    @property
    def iso_test_conditions(self) -> bool:
        """Whether a run is judged against ISO 9283's test conditions: the report heads its banner
        "Deviations from ISO 9283", and a run stored before its results recorded the conditions and
        deviations gets those its parameters, station snapshot and results show."""
        ...

    @property
    def measures_in_motion(self) -> bool:
        """Whether the kind measures while the robot moves (a pose stream, a tool still ringing after
        "done"): a simulated cell started for its run records the robot twin's dense truth (each
        move's true trajectory), which its analysis compares with; a kind measuring at rest needs none."""
        ...

    @property
    def history_figures(self) -> tuple[str, ...]:
        """The figures per point ``instrument history`` and the web view's robot history follow (keys of
        the ISO figures, ``rp_l`` ...); empty: the kind's runs are not in a robot's history."""
        ...

    def title(self, parameters: Mapping[str, Any], results: Mapping[str, Any] | None) -> str:
        """What a run measured, for the report's title: from the parameters it ran with (as stored, so
        ``--set cycles=3`` gives 3 cycles) and, once it has finished, its results."""
        ...
