"""The ``StepContext`` a procedure kind measures through, on a real (or fake) station.

Motion runs at the procedure's speed and within its timeouts; waits end early on an abort; a pose
is measured from ``frames_per_pose`` frame triples, retried when frames fail (with a back-off:
``retry_wait``), corrected with the calibration records in force, and failed frames are kept as the
procedure asks.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from drivers.camera import Frame, GrabFailed
from drivers.interferometer import Interferometer
from drivers.robot import MotionEnvelope, Robot
from drivers.rotary_table import RotaryTable
from instrument import COMPONENTS, SCREENS
from procedures.engine._live_frames import write_live_frames
from procedures.engine._streaming import Tracker, acquire_stream, compensate_with, distance_to, seconds_of
from procedures.kinds import MotionParameters, PoseReading, Step, StreamRecord, retry_wait
from procedures.station import (
    Compensator,
    MeasurementFailed,
    PoseMeasurement,
    RunError,
    Science,
    StationFile,
    StationRuntime,
)
from procedures.store import CorrectedPose, ExposureEvidence, FrameExposure, PoseQuality, SolvedPose, as_pose

S = TypeVar("S")


def robot_speed(envelope: MotionEnvelope, params: MotionParameters) -> tuple[float, float]:
    """Linear speed (m/s) and acceleration (m/s²) of the run: its percentages of the envelope's caps."""
    return (envelope.max_speed * params.speed_percent / 100.0,
            envelope.max_acceleration * params.acceleration_percent / 100.0)


class StationStepContext:
    """A ``StepContext`` on a ``StationRuntime``.

    Parameters
    ----------
    station : the devices, opened on first use
    params : the run's motion and measurement parameters
    science : locates and solves frame triples
    compensators : the calibration records in force (empty: poses are not corrected)
    wait : sleeps, raising when the run is aborted meanwhile
    check_abort : raises when the run has been aborted
    log : ``log(kind, message)`` into the run's events
    run_dir : the run's folder; saved frames go to its ``frames/``
    emit : ``emit(event, **data)`` to the run's listener (the live ``stream`` events), optional
    """

    def __init__(self, station: StationRuntime, params: MotionParameters, science: Science, *,
                 compensators: Sequence[Compensator], wait: Callable[[float], None],
                 check_abort: Callable[[], None], log: Callable[[str, str], None], run_dir: Path,
                 emit: Callable[..., Any] | None = None) -> None:
        self._station, self._params, self._science = station, params, science
        self._compensators = list(compensators)
        self._wait, self._check_abort, self._log, self._run_dir = wait, check_abort, log, run_dir
        self._emit = emit
        self._states: dict[type, Any] = {}  # the kind's (and its helpers') memory of this session, by type
        # Host wall-clock times of the last motion (sent, done): what a measured frame must be newer than.
        self._motion_started: float | None = None
        self._motion_ended: float | None = None
        self._session_started = time.time()

    def session_state(self, state: type[S]) -> S:
        if state not in self._states:
            self._states[state] = state()
        found: S = self._states[state]
        return found

    def wait(self, seconds: float) -> None:
        self._wait(seconds)

    def log(self, kind: str, message: str) -> None:
        self._log(kind, message)

    @property
    def station(self) -> StationFile:
        return self._station.model

    @property
    def robot(self) -> Robot:
        return self._station.robot

    @property
    def table(self) -> RotaryTable:
        return self._station.table

    @property
    def interferometer(self) -> Interferometer:
        return self._station.interferometer

    def move_robot(self, tcp_pose: Sequence[float]) -> None:
        speed, acceleration = robot_speed(self._station.envelope, self._params)
        target = np.asarray(tcp_pose, dtype=float)
        self._motion(lambda: self.robot.move_linear(target, speed, acceleration, timeout=self._params.move_timeout_s))

    def turn_table(self, angle: float, speed: float) -> None:
        table = self.table

        def turn() -> None:
            table.move_absolute(angle, speed=speed)
            table.wait_in_position(timeout=self._params.move_timeout_s)

        self._motion(turn)

    def _motion(self, move: Callable[[], None]) -> None:
        """Run a blocking ``move``, noting when it was sent and when it was done (the frames measured next
        must be proven newer: ``exposure_evidence``)."""
        self._motion_started, self._motion_ended = time.time(), None
        move()
        self._motion_ended = time.time()

    def settle(self) -> None:
        self._wait(self._params.settle_time_s)

    def measure_pose(self, step: Step, *, direction: Mapping[str, int | None] | None = None,
                     expected: Mapping[int, float] | None = None) -> PoseReading:
        p = self._params
        last_error, frames_saved = "", []
        for attempt in range(p.retries_per_pose + 1):
            if attempt > 0:
                self._wait(retry_wait(p, attempt - 1))
            self._check_abort()
            triples: list[dict[str, Frame]] = []
            try:
                for _ in range(p.frames_per_pose):
                    triples.append({s: self._station.camera(s).grab(timeout=p.grab_timeout_s) for s in SCREENS})
                exposure, unproven = self._exposure_evidence(triples)
                if unproven:  # a frame not proven to show the scene after the motion: never a good sample
                    raise MeasurementFailed(unproven)
                measurements = [self._science.measure(triple) for triple in triples]
            except (MeasurementFailed, GrabFailed) as exc:
                last_error = f"attempt {attempt + 1}: {exc}"
                self._log("measure_failed", f"{step.key}: {last_error}")
                if p.save_frames != "never":
                    frames_saved += self._save_frames(step, triples, f"failed{attempt}")
                if triples:  # the live view shows what the cameras saw, even when no cross was found
                    write_live_frames(self._run_dir, step.index, step.key, {s: f.image for s, f in triples[-1].items()})
                continue
            write_live_frames(self._run_dir, step.index, step.key, {s: f.image for s, f in triples[-1].items()},
                              measurements[-1].crosses)
            solved = _solved(measurements, attempts=attempt + 1, exposure=exposure)
            implausible = _implausible(solved.pose, expected, p)
            if implausible:  # a frame of another pose (stale, or another target): never a good sample
                last_error = f"attempt {attempt + 1}: {implausible}"
                self._log("measure_failed", f"{step.key}: {last_error}")
                if p.save_frames != "never":
                    frames_saved += self._save_frames(step, triples, f"failed{attempt}")
                continue
            if p.save_frames == "always":
                frames_saved += self._save_frames(step, triples, "ok")
            stamps = [f.timestamp for t in triples for f in t.values()]
            return PoseReading(ok=True, solved=solved, corrected=self._corrected(solved.pose, direction),
                               crosses={s: [m.crosses.get(s) for m in measurements] for s in SCREENS},
                               frames=frames_saved or None, t_measured=float(np.mean(stamps)), attempts=attempt + 1)
        return PoseReading(ok=False, error=last_error, frames=frames_saved or None, attempts=p.retries_per_pose + 1)

    def _exposure_evidence(self, triples: Sequence[Mapping[str, Frame]]) -> tuple[ExposureEvidence, str]:
        """The frames' proof of showing the scene after the last motion, and what is not proven ("" if all is).

        A frame that shows a scene still since a time (the simulated file cameras' stamp) must be still since
        the motion was sent at the latest: the only still scene after that is the motion's end. A frame whose
        exposure started at a time must have started after the motion was reported done. A frame with
        neither is no proof (the camera gives no exposure time: a hardware trigger without stamps).
        """
        started = self._motion_started if self._motion_started is not None else self._session_started
        ended = self._motion_ended if self._motion_ended is not None else self._session_started
        exposures, problems = [], []
        for triple in triples:
            for screen, frame in triple.items():
                if frame.exposure_start is None or frame.evidence not in ("still since", "exposure"):
                    problems.append(f"camera {screen}: its frame carries no evidence of when it was exposed "
                                    "(use a software trigger or the camera's embedded frame stamps)")
                    continue
                exposures.append(FrameExposure(screen, float(frame.exposure_start), str(frame.evidence)))
                bound, event = (started, "was sent") if frame.evidence == "still since" else (ended, "was done")
                if frame.exposure_start < bound:
                    problems.append(f"camera {screen}: the frame shows the scene as it was "
                                    f"{bound - frame.exposure_start:.3f} s before the motion {event} (a stale frame)")
        evidence = ExposureEvidence(self._motion_started, self._motion_ended, tuple(exposures))
        return evidence, "; ".join(dict.fromkeys(problems))

    def stream_motion(self, step: Step, motion: Callable[[], None], *, rate_hz: float, exposure_s: float,
                      hold_s: float, target_in_m: Sequence[float] | None = None,
                      direction: Mapping[str, int | None] | None = None) -> StreamRecord:
        """Stream the cameras while ``motion()`` runs and ``hold_s`` after it (``acquire_stream``); the
        poses corrected with the records in force for the approach ``direction``. One ``stream`` event
        per streamed second goes to the listener (``distance_to_target`` from ``target_in_m``)."""
        tracker = self._tracker(compensate_with(self._compensators, direction))

        def start() -> Any:
            try:
                return self._station.camera_stream(rate_hz, exposure_s=exposure_s, timeout=self._params.grab_timeout_s)
            except ValueError as exc:  # a camera that cannot stream, a rate out of range: the station's problem
                raise RunError(f"{step.key}: cannot stream the cameras: {exc}") from None

        record = acquire_stream(start, motion, robot=self.robot, hold_s=hold_s, wait=self._wait, tracker=tracker,
                                exposure_s=dict.fromkeys(SCREENS, exposure_s), check_abort=self._check_abort)
        self._announce(step, record, target_in_m)
        return record

    def _tracker(self, compensate: Callable[[np.ndarray], np.ndarray] | None) -> Tracker:
        factory = getattr(self._science, "pose_tracker", None)  # a test's fake core brings its own
        if factory is not None:
            tracker: Tracker = factory(compensate=compensate)
            return tracker
        from instrument.pose import Geometry
        from instrument.stream import PoseTracker

        # The cameras' own clocks here (the stream retimes the samples once the clock models are fitted).
        return PoseTracker(Geometry.from_dict(self._station.model.geometry), compensate=compensate,
                           max_timestamp_spread=1e9)

    def _announce(self, step: Step, record: StreamRecord, target_in_m: Sequence[float] | None) -> None:
        if self._emit is None or not len(record):
            return
        distance = distance_to(record, np.asarray(target_in_m)) if target_in_m is not None else None
        for i in seconds_of(record):
            self._emit("stream", step=step.index, key=step.key, t=float(record.t[i]),
                       pose=[float(v) for v in record.pose[i]],
                       quality={"residual_rms": float(record.residual_rms[i]),
                                "timestamp_spread": float(record.timestamp_spread[i]),
                                "tracked": int(record.tracked[i])},
                       rate_hz=record.meta.get("rate_hz"), dropped=record.dropped,
                       distance_to_target=None if distance is None else float(distance[i]))

    def _corrected(self, pose: Sequence[float], direction: Mapping[str, int | None] | None) -> CorrectedPose | None:
        if not self._compensators:
            return None
        corrected, flags = np.asarray(pose), []
        for compensator in self._compensators:
            corrected, more = compensator.correct(corrected, direction)
            flags += list(more)
        return CorrectedPose(pose=as_pose(corrected), flags=tuple(str(f) for f in flags),
                             records=tuple(c.record_id for c in self._compensators),
                             direction=None if direction is None else dict(direction))

    def _save_frames(self, step: Step, triples: Sequence[Mapping[str, Frame]], tag: str) -> list[str]:
        folder = self._run_dir / "frames"
        folder.mkdir(exist_ok=True)
        stem = f"{step.index:05d}_{re.sub(r'[^A-Za-z0-9]+', '-', step.key)}_{tag}"
        saved = []
        for number, triple in enumerate(triples):
            for screen, frame in triple.items():
                path = folder / f"{stem}_{number}_{screen}.npy"
                np.save(path, np.asarray(frame.image))
                saved.append(str(Path("frames") / path.name))
        return saved


def _implausible(pose: Sequence[float], expected: Mapping[int, float] | None, params: MotionParameters) -> str:
    """Why a solved pose cannot be the one the devices were sent to ("" if it can): a coordinate farther than
    ``plausibility_mm`` (positions) or ``plausibility_deg`` (angles) from its expected raw value. The limits
    sit far above the raw instrument's error (tens of µm and arc-seconds) and below one calibration step
    (5 mm, 0.25°), so a frame left from the previous pose is caught."""
    if not expected:
        return ""
    limits = (params.plausibility_mm * 1e-3, float(np.radians(params.plausibility_deg)))
    off = []
    for index, value in sorted(expected.items()):
        limit = limits[index >= 3]
        delta = float(pose[index]) - float(value)
        if limit > 0 and abs(delta) > limit:
            name = COMPONENTS[index]
            off.append(f"{name} {delta * 1e3:+.3f} mm" if index < 3 else f"{name} {np.degrees(delta):+.4f}°")
    if not off:
        return ""
    return (f"the measured pose is not where the devices were sent ({', '.join(off)}; limits "
            f"{params.plausibility_mm:g} mm, {params.plausibility_deg:g}°): a stale or wrong frame")


def _solved(measurements: Sequence[PoseMeasurement], *, attempts: int,
            exposure: ExposureEvidence | None = None) -> SolvedPose:
    """The mean pose of the frame triples, with their spread and each one's pose: the core's results, typed."""
    poses = np.array([m.pose for m in measurements])
    quality = PoseQuality(residual_rms=float(np.mean([m.residual_rms for m in measurements])),
                          pose_std=as_pose(poses.std(axis=0)), attempts=attempts, exposure=exposure)
    return SolvedPose(pose=as_pose(poses.mean(axis=0)), quality=quality, per_frame=tuple(as_pose(p) for p in poses),
                      components=COMPONENTS)
