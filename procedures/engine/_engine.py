"""The run engine: dry run, then the plan's steps, each sample committed before the next motion.

The engine drives any ``ProcedureKind``: it asks the kind for the plan, establishes each step's
set-up, lets the kind move and measure, commits the sample, and hands the samples to the kind's
analysis at the end. It knows no kind by name.

States (``RunState``): QUEUED → RUNNING → (PAUSED ⇄ RUNNING) → FINISHED | FAILED | ABORTED.
Pauses happen only at safe points (between poses): on request (one Ctrl-C), when the robot
reports a protective stop, or when a device stops answering or loses its connection mid-step
(``DeviceTimeout``, ``DeviceConnectionError``: the run can go on once it is back, so it is not
FAILED); the step is then measured again. An abort (two Ctrl-C, SIGTERM/SIGHUP, or the cell) stops the robot and
the table first, whatever else fails.

Each ``execute()`` is one **session** of the run. A session skips the steps stored as measured
and measures every other one, including steps a previous session stored as failed (their failed
sample is kept as superseded). ``max_failed_samples`` counts the failed poses of this session only,
so a resumed run is never failed by the failures it came to repair. Every state change is a
compare-and-set on the state this engine last wrote and on its lease (``RunStore``).
"""

from __future__ import annotations

import threading
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np

from drivers import ClientLibraryMissing, DeviceConnectionError, DeviceError, DeviceTimeout
from drivers.robot import EmergencyStop, ProtectiveStop
from instrument import __version__
from procedures.engine._dry_run import collapse, plan_problems
from procedures.engine._hooks import HookRunner
from procedures.engine._step_context import StationStepContext
from procedures.kinds import RESTING_SETUP, AnalysisContext, PoseReading, ProcedureBase, Setup, Step, kind_of
from procedures.station import (
    Compensator,
    DryRunFailed,
    Event,
    InputRefused,
    ResumeRefused,
    RunAborted,
    RunError,
    Science,
    StationFile,
    StationRuntime,
    TruthLog,
)
from procedures.store import (
    RESUMABLE_STATES,
    Commanded,
    DuplicateStep,
    Lease,
    RunState,
    RunStore,
    Sample,
    StoreError,
    StoreFull,
    StoreLocked,
    StoreTrouble,
    as_pose,
)

PauseDecision = Literal["resume", "abort", "detach"]
"""What a paused run does next: continue, abort (devices stopped), or stay PAUSED for ``instrument resume``."""

_MAX_PROBLEMS_SHOWN = 50
_PLURAL = {"cycle": "cycles", "axis": "axes", "group": "groups", "repeat": "repeats"}


class _Detached(Exception):
    """The run stays PAUSED in the store; ``instrument resume`` continues it later."""


def record_paths(station: StationFile) -> list[str]:
    """The calibration record files the station's ``calibration.record`` names (one path, a list, or none)."""
    record = station.calibration.record
    return [] if not record else ([record] if isinstance(record, str) else list(record))


def compensators_in_force(station: StationFile, science: Science) -> list[Compensator]:
    """The compensators of the station's calibration records; a record that cannot be read is a ``RunError``."""
    compensators = []
    for path in record_paths(station):
        try:
            compensators.append(science.load_compensator(path))
        except InputRefused as exc:
            raise RunError(f"calibration.record: {exc}") from None
        except OSError as exc:
            raise RunError(f"calibration.record: cannot read {path}: {exc.strerror or exc}") from None
        except (ValueError, KeyError, TypeError) as exc:
            raise RunError(f"calibration.record: {path} is not a calibration record: {exc}") from None
    return compensators


def _truth_log(station: StationFile) -> TruthLog | None:
    """The simulated cell's truth, from every cell the run was measured on (a resumed run may have
    been measured on several; their logs are merged by time)."""
    sim = station.simulation
    if sim is None:
        return None
    paths = [path for path in [*sim.earlier_truth_logs, sim.truth_log] if path and Path(path).is_file()]
    return TruthLog.read(*paths) if paths else None


def create_run(store: RunStore, procedure: ProcedureBase, station: StationRuntime, science: Science, *,
               procedure_file: str | None = None, procedure_text: str | None = None,
               station_path: str | None = None) -> str:
    """Queue a run: plan it (so its size is known), snapshot everything it depends on."""
    kind = kind_of(procedure)
    plan = kind.plan(procedure.parameters, station.model)
    record_ids = None
    if kind.applies_compensation(procedure.parameters):
        record_ids = ",".join(c.record_id for c in compensators_in_force(station.model, science)) or None
    return store.create_run(
        procedure=procedure.procedure, procedure_name=procedure.name, procedure_file=procedure_file,
        procedure_text=procedure_text, parameters=procedure.parameters.model_dump(),
        station=station.model.model_dump(), station_name=station.model.name, station_path=station_path,
        software_version=__version__, calibration_record_id=record_ids, total_steps=len(plan),
    )


class RunEngine:
    """Execute (or continue) one stored run.

    Parameters
    ----------
    store, run_id : where the run lives
    procedure : the validated procedure file (rebuilt from the stored text on resume)
    station : the devices, envelope and operator
    science : the measurement core (``procedures.station._science.InstrumentScience``, or a fake)
    hooks : HookRunner, optional
    listener : callable(event dict), optional
        Progress, state changes and samples, for the terminal or ``--jsonl``.
    pause_handler : callable(engine) -> "resume" | "abort" | "detach", optional
        Decides what happens once the run is paused; default: wait for ``resume()`` or
        ``request_abort()`` from another thread, up to ``pause_timeout_s``, then detach.
    """

    def __init__(self, store: RunStore, run_id: str, procedure: ProcedureBase, station: StationRuntime,
                 science: Science, *, hooks: HookRunner | None = None,
                 listener: Callable[[dict[str, Any]], None] | None = None,
                 pause_handler: Callable[[RunEngine], PauseDecision] | None = None,
                 pause_timeout_s: float = 3600.0, lease: Lease | None = None) -> None:
        self.store, self.run_id, self.procedure, self.station, self.science = store, run_id, procedure, station, science
        self.kind = kind_of(procedure)
        self.params = procedure.parameters
        self.hooks = hooks or HookRunner()
        self.listener = listener
        self.pause_handler = pause_handler
        self.pause_timeout_s = pause_timeout_s
        self.lease = lease
        self.state = RunState(store.get_run(run_id)["state"])
        self.resumes = 0  # pauses this session has come back from (the Ctrl-C handler counts presses per resume)
        self.ending = False  # the session is being ended (its outcome is being recorded, or is)
        self.session_failures = 0
        self._pause_request = threading.Event()
        self._pause_reason = "operator request"
        self._abort_request = threading.Event()
        self._abort_reason = "operator request"
        self._resume_request = threading.Event()
        self._setup: Setup | None = None
        self._durations: list[float] = []  # of this session's steps, their set-ups left out
        self._setup_durations: list[float] = []
        self.compensators: list[Compensator] = []
        self.plan: list[Step] = []

    # -------------------------------------------------------------------------- control (any thread)
    def request_pause(self, reason: str = "operator request") -> None:
        self._pause_reason = reason
        self._pause_request.set()

    def request_abort(self, reason: str = "operator request") -> None:
        self._abort_reason = reason
        self._abort_request.set()

    def resume(self) -> None:
        self._resume_request.set()

    # ----------------------------------------------------------------------------------- helpers
    def _emit(self, event: str, **data: Any) -> dict[str, Any]:
        payload = {"event": event, "run_id": self.run_id, "procedure": self.procedure.procedure,
                   "time": time.time(), **data}
        if self.listener:
            try:
                self.listener(payload)
            except Exception:
                pass  # a broken display must not stop a measurement
        return payload

    def _set_state(self, state: RunState, *, reason: str | None = None, hook: Event | None = None) -> None:
        # Compare-and-set: only from the state this engine last wrote, and only while it holds the lease.
        self.store.set_state(self.run_id, state, reason=reason, expected=self.state, lease=self.lease)
        self.state = state
        payload = self._emit("state", state=state, reason=reason)
        if hook:
            self.hooks.emit({**payload, "event": hook})

    def _wait(self, seconds: float) -> None:
        """Sleep, but an abort request cuts it short."""
        if seconds > 0 and self._abort_request.wait(seconds):
            raise RunAborted(self._abort_reason)

    def _check_abort(self) -> None:
        if self._abort_request.is_set():
            raise RunAborted(self._abort_reason)

    def _log(self, kind: str, message: str) -> None:
        self.store.log(self.run_id, kind, message)

    def _log_hook_failures(self) -> None:
        for message in self.hooks.take_failures():
            self.store.log(self.run_id, "hook_failed", message)

    # ------------------------------------------------------------------------------------- run
    def execute(self) -> RunState:
        """Run to the end (or to a pause that is detached): one session. Returns the final state."""
        run = self.store.get_run(self.run_id)
        stored = RunState(run["state"])
        if not stored.resumable:
            raise RunError(f"run {self.run_id} is {stored}; only {', '.join(RESUMABLE_STATES)} runs can be continued")
        self.state = stored
        measured = self.store.measured_steps(self.run_id)
        to_repeat = self.store.committed_steps(self.run_id) - measured  # failed in an earlier session
        resuming = bool(measured or to_repeat) or stored != RunState.QUEUED
        self.session_failures = 0
        last_failure = ""
        self.ending = False
        started = False  # whether this session has changed the run's state yet
        try:
            self.science.configure(self.station.model)
            self.plan = self.kind.plan(self.params, self.station.model)
            if run["total_steps"] is not None and run["total_steps"] != len(self.plan):
                raise RunError(f"the plan now has {len(self.plan)} steps, the stored run {run['total_steps']}: "
                               "procedure or station changed; cannot resume")
            if self.kind.applies_compensation(self.params):
                self.compensators = compensators_in_force(self.station.model, self.science)
            context = StationStepContext(self.station, self.params, self.science, compensators=self.compensators,
                                         wait=self._wait, check_abort=self._check_abort, log=self._log,
                                         run_dir=self.store.run_dir(self.run_id), emit=self._emit)
            reason = None
            if resuming:
                reason = f"resumed after {len(measured)} measured samples" + (
                    f"; {len(to_repeat)} failed poses to measure again" if to_repeat else "")
                self.dry_run(measured)  # before the state changes: a resume that cannot start leaves it alone
            started = True
            self._set_state(RunState.RUNNING, hook="run_resumed" if resuming else "run_started", reason=reason)
            if not resuming:
                self.dry_run(measured)
            # Every kind records the cell's robot: a run that does not move it (the angle calibration) still
            # belongs to that robot's cell, and the faces group runs by it (a robot listed once, not twice).
            self._record_robot_identity(run, required="robot" in self.kind.devices(self.params))
            for step in self.plan:
                if step.index in measured:
                    continue
                self._safe_point()
                while True:
                    try:
                        pose = self._do_step(step, context, repeat=step.index in to_repeat)
                        break
                    except (ProtectiveStop, EmergencyStop) as exc:
                        self.station.safe_state()
                        self._pause(f"{type(exc).__name__}: {exc}")  # then retry the same step
                    except (DeviceTimeout, DeviceConnectionError) as exc:
                        if isinstance(exc, ClientLibraryMissing):
                            raise
                        self._pause_on_device(exc)  # then retry the same step
                self._log_hook_failures()
                if self.lease is not None:
                    self.store.renew_lease(self.lease)
                if not pose.ok:
                    self.session_failures += 1
                    last_failure = f"{step.key}: {pose.error}"
                if self.session_failures > self.params.max_failed_samples:
                    raise RunError(f"{self.session_failures} poses could not be measured in this session (limit "
                                   f"max_failed_samples = {self.params.max_failed_samples}; the last: "
                                   f"{last_failure}); resume to measure them again")
            self._safe_point()
            if self._setup is not None:
                RESTING_SETUP.establish(self._setup, self.station)  # e.g. the OPR back from the table
            self._analyse()
            self._set_state(RunState.FINISHED, hook="run_finished")
        except _Detached:
            pass
        except StoreError as exc:
            if isinstance(exc, DuplicateStep):  # not trouble with the store: a step written twice is a defect
                self._end_with(exc)
            elif not started:  # nothing was moved and the run's state is as it was: the store's one line
                raise
            else:
                self._pause_on_store(exc)
        except Exception as exc:
            if started or not resuming or isinstance(exc, (RunAborted, KeyboardInterrupt)):
                self._end_with(exc)
            else:  # nothing was moved, nothing changed: the run stays as it was, the reason logged
                why = str(exc) if isinstance(exc, (DeviceError, RunError)) else f"{type(exc).__name__}: {exc}"
                self._log("resume_refused", why)
                raise ResumeRefused(f"run {self.run_id} was not resumed (it stays {stored}): {why}") from None
        except KeyboardInterrupt as exc:
            self._end_with(exc)
        finally:
            self.ending = True  # the outcome is stored: a late SIGTERM must not cut the hooks' last words
            self.hooks.close()  # bounded by the longest hook deadline; undelivered events are reported
            try:
                self._log_hook_failures()
            except StoreError:
                pass  # the store's own trouble is what the session ends with
        return self.state

    def _pause_on_store(self, exc: StoreError) -> None:
        """The store failed mid-run (disk full, locked by another process, damaged, read-only): robot and
        table stopped first, then the run PAUSED with the store's one line and what to do. When not even the
        pause can be recorded, a ``StoreTrouble`` says so (the run then shows RUNNING; resume continues it)."""
        self.ending = True
        problems = self.station.safe_state()
        if isinstance(exc, StoreFull):
            self.store.make_room()  # the store's reserve: room for the pause and its reason
            todo = "free space, then: "
        elif isinstance(exc, StoreLocked):
            todo = "end that process's transaction, then: "
        elif isinstance(exc, StoreTrouble):
            todo = "once the disk is sound: "
        else:
            todo = "repair the store, then: "
        reason = f"{exc}; {todo}instrument resume {self.run_id}" + ("; " + "; ".join(problems) if problems else "")
        # The devices are stopped: waiting for another process's lock to go is safe.
        deadline = time.monotonic() + 4 * float(getattr(self.store, "timeout", 30.0))
        while True:
            try:
                self._set_state(RunState.PAUSED, reason=reason, hook="run_paused")
                return
            except StoreLocked as again:
                if time.monotonic() < deadline:
                    continue
                last: StoreError = again
            except StoreError as again:
                last = again
            raise StoreTrouble(f"{reason} (robot and table stopped; the run could not be marked PAUSED: {last}; "
                               "it shows RUNNING until resumed)") from None

    def _end_with(self, exc: BaseException) -> None:
        """End the session on ``exc`` (called while it is handled): FAILED after a failed dry run (no device
        was touched), ABORTED on an abort, FAILED on anything else (a bug's traceback goes to the log)."""
        if isinstance(exc, DryRunFailed):
            self._end(RunState.FAILED, str(exc), "run_failed", stop_devices=False)
        elif isinstance(exc, (RunAborted, KeyboardInterrupt)):
            self._end(RunState.ABORTED, str(exc) or "interrupted", "run_aborted")
        else:
            expected = isinstance(exc, (DeviceError, RunError))
            if not expected:  # a bug or an unforeseen failure: the operator gets one line, the log the traceback
                self._log("traceback", traceback.format_exc())
            self._end(RunState.FAILED, str(exc) if expected else f"{type(exc).__name__}: {exc}", "run_failed")

    def _end(self, state: RunState, reason: str, hook: Event, *, stop_devices: bool = True) -> None:
        """End the session early: devices stopped first, then the state and reason stored."""
        self.ending = True
        problems = self.station.safe_state() if stop_devices else []
        self._set_state(state, reason=reason + ("; " + "; ".join(problems) if problems else ""), hook=hook)

    def _streams(self, steps: Sequence[int] | None = None) -> dict[int, Any]:
        return dict(self.store.streams(self.run_id, steps))

    def _analyse(self) -> None:
        started = time.monotonic()

        def progress(stage: str, done: int, total: int) -> None:
            """The analysis' own progress and ETA (at the pace of its passes so far) for the faces."""
            elapsed = time.monotonic() - started
            eta = elapsed / done * (total - done) if done > 0 else None
            self._emit("analysis", stage=stage, done=done, total=total, eta_s=eta)

        self._emit("analysis", stage="results", done=0, total=None, eta_s=None)
        context = AnalysisContext(run_id=self.run_id, station=self.station.model, science=self.science,
                                  compensators=self.compensators, run_dir=self.store.run_dir(self.run_id),
                                  truth=_truth_log(self.station.model),
                                  streams=self._streams, sessions=self.store.sessions(self.run_id),
                                  progress=progress)
        analysis = self.kind.analyse(self.store.samples(self.run_id), self.params, context)
        if analysis.calibration_record_id is not None:
            self.store.update_run(self.run_id, calibration_record_id=analysis.calibration_record_id)
        self.store.set_results(self.run_id, analysis.results)

    # -------------------------------------------------------------------------------- dry run
    def dry_run(self, committed: set[int] | frozenset[int] = frozenset()) -> None:
        """Check the whole remaining plan before any motion (see ``procedures.engine._dry_run``);
        raises ``DryRunFailed`` listing the problems."""
        todo = [s for s in self.plan if s.index not in committed]
        found = plan_problems(todo, self.kind.devices(self.params), self.station, self.science, self.params)
        problems = collapse(found)
        self.store.log(self.run_id, "dry_run", f"{len(todo)} steps checked, {len(found)} problems",
                       {"problems": problems[:200]})
        self._emit("dry_run", steps=len(todo), problems=problems[:200])
        if problems:
            more = len(problems) - _MAX_PROBLEMS_SHOWN
            raise DryRunFailed(problems[:_MAX_PROBLEMS_SHOWN] + ([f"... and {more} more"] if more > 0 else []))

    # ------------------------------------------------------------------------------- pausing
    def _safe_point(self) -> None:
        self._check_abort()
        if self._pause_request.is_set():
            self._pause(self._pause_reason)

    def _pause_on_device(self, exc: DeviceError) -> None:
        """A device stopped answering or lost its connection mid-step: nothing measured is lost and the
        step can be measured again once it is back, so robot and table are stopped and the run PAUSED
        with the device's one line and what to do (not FAILED)."""
        problems = self.station.safe_state()
        self._pause(f"{exc}; once {exc.device} answers again: instrument resume {self.run_id}"
                    + ("; " + "; ".join(problems) if problems else ""))

    def _pause(self, reason: str) -> None:
        self._pause_request.clear()
        self._resume_request.clear()
        self._set_state(RunState.PAUSED, reason=reason, hook="run_paused")
        decision: PauseDecision
        if self.pause_handler is not None:
            decision = self.pause_handler(self)
        else:
            decision = "detach"
            deadline = time.monotonic() + self.pause_timeout_s
            while time.monotonic() < deadline:
                if self._abort_request.is_set():
                    decision = "abort"
                    break
                if self._resume_request.wait(0.05):
                    decision = "resume"
                    break
        if decision == "abort" or self._abort_request.is_set():
            raise RunAborted(self._abort_reason if self._abort_request.is_set() else "aborted while paused")
        if decision == "detach":
            self.store.log(self.run_id, "detached", "left paused; continue with `instrument resume`")
            raise _Detached()
        self.resumes += 1
        self._set_state(RunState.RUNNING, reason="resumed", hook="run_resumed")

    # ---------------------------------------------------------------------------------- steps
    def _establish(self, setup: Setup) -> None:
        started = time.monotonic()
        setup.establish(self._setup, self.station)
        self._setup_durations.append(time.monotonic() - started)
        self.store.log(self.run_id, "setup", str(setup))
        self._emit("setup", setup=str(setup))
        self._setup = setup

    def _do_step(self, step: Step, context: StationStepContext, *, repeat: bool = False) -> PoseReading:
        """Move, measure and commit one step; ``repeat``: it failed in an earlier session."""
        t_start = time.time()
        setups_before = sum(self._setup_durations)
        new_setup = step.setup != self._setup
        if new_setup and not step.setup.after_motion:
            self._establish(step.setup)
        self._check_abort()
        self.kind.move(step, self.params, context)
        if new_setup and step.setup.after_motion:
            self._establish(step.setup)
        reading = self.kind.measure(step, self.params, context)
        pose = reading.pose
        nominal = step.meta.get("nominal")
        commanded = Commanded(tcp_pose=None if step.tcp_pose is None else as_pose(step.tcp_pose),
                              table_angle=step.table_angle, nominal=None if nominal is None else float(nominal))
        sample = Sample(run_id=self.run_id, step_index=step.index, step_key=step.key, phase=step.phase,
                        label=step.label, ok=pose.ok, error=pose.error, commanded=commanded, solved=pose.solved,
                        corrected=pose.corrected, crosses=pose.crosses, reference=reading.reference, meta=step.meta,
                        frames=tuple(pose.frames or ()), t_start=t_start, t_measured=pose.t_measured)
        self.store.add_sample(sample, stream=None if reading.stream is None else reading.stream.to_stored(),
                              session=reading.session)
        # Committed: from here on nothing can lose this sample.
        if repeat:
            self._log("remeasured", f"{step.key}: failed in an earlier session, measured again "
                                    f"({'ok' if pose.ok else 'failed again'}); the failed sample is kept as superseded")
        self._durations.append(time.time() - t_start - (sum(self._setup_durations) - setups_before))
        event = self._emit("point_measured", step=step.index, key=step.key, label=step.label, ok=pose.ok,
                           error=pose.error, pose=None if pose.pose is None else list(pose.pose),
                           residual_rms=None if pose.solved is None else pose.solved.quality.residual_rms,
                           reference=reading.reference.value)
        self.hooks.emit(event)
        self._emit_progress(step)
        return pose

    def _record_robot_identity(self, run: dict[str, Any], *, required: bool = True) -> None:
        """Store who the robot is, as its controller says (a run measured on another robot is refused).

        ``required`` False (a kind that does not use the robot): a robot that cannot be reached or tells no
        identity is logged, and a different robot than the stored one is logged and left as stored."""
        try:
            identify = getattr(self.station.robot, "identity", None)
        except DeviceError as exc:
            if required:
                raise
            self._log("robot_identity", f"the cell's robot was not reached, the run records no robot: {exc}")
            return
        if identify is None:
            self._log("robot_identity", "the robot adapter cannot tell its identity")
            return
        try:
            identity = identify()
        except DeviceError as exc:  # an older controller: the run goes on without it
            self._log("robot_identity", f"the controller did not give its identity: {exc}")
            return
        stored = run.get("robot_serial")
        if stored and stored != identity.serial_number and not required:
            self._log("robot_identity", f"the cell's robot now reports serial {identity.serial_number}; the run "
                                        f"keeps {stored}")
            return
        if stored and stored != identity.serial_number:
            raise RunError(f"this run was measured on the robot with serial {stored}; the controller now reports "
                           f"serial {identity.serial_number}: resume it on that robot")
        self.store.update_run(self.run_id, robot_manufacturer=identity.manufacturer, robot_model=identity.model,
                              robot_serial=identity.serial_number,
                              robot_controller_version=identity.controller_version)
        self._log("robot_identity", f"{identity.manufacturer} {identity.model}, serial {identity.serial_number}, "
                                    f"controller {identity.controller_version}")

    def _emit_progress(self, step: Step) -> None:
        """Progress with where the run is in its plan (phase k/N, cycle, axis, group) and an ETA that
        counts the set-ups still to come (each at the mean of those made so far)."""
        done = len(self.store.committed_steps(self.run_id))
        total = len(self.plan)
        recent = self._durations[-20:]
        pace = float(np.mean(recent)) if recent else None
        remaining = self.plan[step.index + 1:]
        setups_left = sum(1 for before, after in zip([step, *remaining], remaining) if after.setup != before.setup)
        setup_s = float(np.mean(self._setup_durations)) if self._setup_durations else 0.0
        eta = None if pace is None else pace * (total - done) + setup_s * setups_left
        phases = list(dict.fromkeys(s.phase for s in self.plan))
        where = {key: step.meta[key] for key in ("cycle", "axis", "group", "repeat") if key in step.meta}
        extent = {_PLURAL[key]: len({s.meta.get(key) for s in self.plan if key in s.meta}) for key in where}
        self._emit("progress", done=done, total=total, eta_s=eta, step=step.index, label=step.label,
                   phase=step.phase, phase_index=phases.index(step.phase) + 1, phases=len(phases),
                   pace_s=pace, setups_left=setups_left, setup_s=setup_s, **where, **extent)
