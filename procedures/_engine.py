"""The run engine: dry run, then the plan's steps, each sample committed before the next motion.

States: QUEUED → RUNNING → (PAUSED ⇄ RUNNING) → FINISHED | FAILED | ABORTED. Pauses happen only at
safe points (between poses): on request (one Ctrl-C), or when the robot reports a protective
stop. An abort (two Ctrl-C, or the cell) stops the robot and the table first, whatever else fails.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from drivers._errors import DeviceError, MotionRefused
from drivers.camera._interface import GrabFailed
from drivers.robot._interface import EmergencyStop, ProtectiveStop
from procedures import _analysis
from procedures._errors import DryRunFailed, RunAborted, RunError
from procedures._geometry import matrix_to_euler, tcp_in_m
from procedures._hooks import HookRunner
from procedures._models import (
    AngleCalibration,
    DisplacementCalibration,
    Iso9283Repeatability,
    ProcedureFile,
)
from procedures._plan import Step, build_plan
from procedures._science import COMPONENTS, MeasurementFailed
from procedures._station import StationRuntime
from procedures._store import RunStore

SCREENS = ("x", "y", "z")
RESUMABLE = ("QUEUED", "RUNNING", "PAUSED", "FAILED")


class _Detached(Exception):
    """The run stays PAUSED in the store; ``instrument resume`` continues it later."""


def software_version() -> str:
    from instrument import __version__

    return __version__


def compensators_in_force(station_model, science) -> list:
    """The compensators named by the station's ``calibration.record`` (a path or a list of paths)."""
    record = station_model.calibration.record
    paths = [] if not record else ([record] if isinstance(record, str) else list(record))
    return [science.load_compensator(path) for path in paths]


def create_run(store: RunStore, procedure: ProcedureFile, station: StationRuntime, science, *,
               procedure_file: str | None = None, procedure_text: str | None = None,
               station_path: str | None = None) -> str:
    """Queue a run: plan it (so its size is known), snapshot everything it depends on."""
    plan = build_plan(procedure, station.model, science)
    record_ids = None
    if isinstance(procedure, Iso9283Repeatability) and procedure.parameters.apply_compensation:
        record_ids = ",".join(c.record_id for c in compensators_in_force(station.model, science)) or None
    return store.create_run(
        procedure=procedure.procedure, procedure_name=procedure.name, procedure_file=procedure_file,
        procedure_text=procedure_text, parameters=procedure.parameters.model_dump(),
        station=station.model.model_dump(), station_name=station.model.name, station_path=station_path,
        software_version=software_version(), calibration_record_id=record_ids, total_steps=len(plan),
    )


class RunEngine:
    """Execute (or continue) one stored run.

    Parameters
    ----------
    store, run_id : where the run lives
    procedure : the validated procedure (rebuilt from the stored text on resume)
    station : StationRuntime (devices, envelope, operator)
    science : Science (see ``procedures._science``)
    hooks : HookRunner, optional
    listener : callable(event dict), optional
        Progress, state changes and samples, for the terminal or ``--jsonl``.
    pause_handler : callable(engine) -> "resume" | "abort" | "detach", optional
        Decides what happens once the run is paused; default: wait for ``resume()`` or
        ``request_abort()`` from another thread, up to ``pause_timeout_s``, then detach.
    """

    def __init__(self, store: RunStore, run_id: str, procedure: ProcedureFile, station: StationRuntime, science,
                 *, hooks: HookRunner | None = None, listener: Callable[[dict], None] | None = None,
                 pause_handler: Callable[[RunEngine], str] | None = None, pause_timeout_s: float = 3600.0) -> None:
        self.store, self.run_id, self.procedure, self.station, self.science = store, run_id, procedure, station, science
        self.params = procedure.parameters
        self.hooks = hooks or HookRunner()
        if self.hooks.on_failure is None:
            self.hooks.on_failure = lambda message, event: self.store.log(self.run_id, "hook_failed", message)
        self.listener = listener
        self.pause_handler = pause_handler
        self.pause_timeout_s = pause_timeout_s
        self.state = store.get_run(run_id)["state"]
        self._pause_request = threading.Event()
        self._pause_reason = "operator request"
        self._abort_request = threading.Event()
        self._abort_reason = "operator request"
        self._resume_request = threading.Event()
        self._setup: str | None = None
        self._table_homed = False
        self._durations: list[float] = []
        self.compensators: list = []
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
    def _emit(self, event: str, **data: Any) -> dict:
        payload = {"event": event, "run_id": self.run_id, "procedure": self.procedure.procedure,
                   "time": time.time(), **data}
        if self.listener:
            try:
                self.listener(payload)
            except Exception:
                pass
        return payload

    def _set_state(self, state: str, *, reason: str | None = None, exit_status: str | None = None,
                   hook: str | None = None) -> None:
        self.state = state
        self.store.set_state(self.run_id, state, reason=reason, exit_status=exit_status)
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

    # ------------------------------------------------------------------------------------- run
    def execute(self) -> str:
        """Run to the end (or to a pause that is detached). Returns the final state."""
        run = self.store.get_run(self.run_id)
        if run["state"] not in RESUMABLE:
            raise RunError(f"run {self.run_id} is {run['state']}; only {', '.join(RESUMABLE)} runs can be continued")
        committed = self.store.committed_steps(self.run_id)
        resuming = bool(committed) or run["state"] != "QUEUED"
        try:
            self.science.configure(self.station.model)
            self.plan = build_plan(self.procedure, self.station.model, self.science)
            if run["total_steps"] is not None and run["total_steps"] != len(self.plan):
                raise RunError(f"the plan now has {len(self.plan)} steps, the stored run {run['total_steps']}: "
                               "procedure or station changed; cannot resume")
            if isinstance(self.procedure, Iso9283Repeatability) and self.params.apply_compensation:
                self.compensators = compensators_in_force(self.station.model, self.science)
            self._set_state("RUNNING", hook="run_resumed" if resuming else "run_started",
                            reason=f"resumed after {len(committed)} committed samples" if resuming else None)
            self.dry_run(committed)
            failed = sum(1 for s in self.store.samples(self.run_id) if not s.ok)
            for step in self.plan:
                if step.index in committed:
                    continue
                self._safe_point()
                while True:
                    try:
                        ok = self._do_step(step)
                        break
                    except (ProtectiveStop, EmergencyStop) as exc:
                        self.station.safe_state()
                        self._pause(f"{type(exc).__name__}: {exc}")  # then retry the same step
                failed += 0 if ok else 1
                if failed > self.params.max_failed_samples:
                    raise RunError(f"{failed} poses could not be measured (limit max_failed_samples = "
                                   f"{self.params.max_failed_samples})")
            self._safe_point()
            if self._setup and self._setup.startswith("table:"):
                self.station.operator.mount_opr("robot")
            results = _analysis.analyse(self)
            self.store.set_results(self.run_id, results)
            self._set_state("FINISHED", exit_status="success", hook="run_finished")
        except _Detached:
            return self.state
        except DryRunFailed as exc:
            self._set_state("FAILED", exit_status="fail", reason=str(exc), hook="run_failed")
        except (RunAborted, KeyboardInterrupt) as exc:
            problems = self.station.safe_state()
            reason = str(exc) or "interrupted"
            self._set_state("ABORTED", exit_status="abort",
                            reason=reason + ("; " + "; ".join(problems) if problems else ""), hook="run_aborted")
        except Exception as exc:
            problems = self.station.safe_state()
            reason = f"{type(exc).__name__}: {exc}" if not isinstance(exc, (DeviceError, RunError)) else str(exc)
            self._set_state("FAILED", exit_status="fail",
                            reason=reason + ("; " + "; ".join(problems) if problems else ""), hook="run_failed")
        return self.state

    # -------------------------------------------------------------------------------- dry run
    def dry_run(self, committed: set[int] = frozenset()) -> None:
        """Check the whole remaining plan before any motion: envelope, speeds, crosses on their
        screens (when the core can predict them), and every device it needs reachable and healthy."""
        problems: list[str] = []
        todo = [s for s in self.plan if s.index not in committed]
        envelope = self.station.envelope
        uses_robot = any(s.tcp_pose is not None for s in todo)
        if uses_robot:
            speed, acceleration = self._robot_speed()
            try:
                envelope.check_speed(speed, acceleration)
            except MotionRefused as exc:
                problems.append(f"speed: {exc.cause}")
        unseen: dict[str, int] = {}
        visibility_checked = True
        for step in todo:
            if step.tcp_pose is None:
                continue
            try:
                envelope.check_pose(np.asarray(step.tcp_pose))
            except MotionRefused as exc:
                problems.append(f"step {step.key}: {exc.cause}")
            if visibility_checked:
                try:
                    opr = matrix_to_euler(tcp_in_m(self.station.reference_tcp_pose, step.tcp_pose))
                    for problem in self.science.visibility_problems(opr):
                        unseen.setdefault(problem, step.index)
                except ImportError:
                    visibility_checked = False
                    self.store.log(self.run_id, "dry_run", "cross visibility not checked: no forward model")
        problems += [f"step {self.plan[i].key}: {p}" for p, i in unseen.items()]
        roles = [f"camera:{s}" for s in SCREENS]
        if uses_robot:
            roles.insert(0, "robot")
        if any(s.table_angle is not None for s in todo):
            roles.append("rotary_table")
        if isinstance(self.procedure, DisplacementCalibration):
            roles.append("interferometer")
        for role in roles:
            try:
                device = self.station.device(role)
                problems += self._health(role, device)
            except Exception as exc:
                problems.append(f"{role}: not reachable: {exc}")
        self.store.log(self.run_id, "dry_run", f"{len(todo)} steps checked, {len(problems)} problems",
                       {"problems": problems[:200]})
        self._emit("dry_run", steps=len(todo), problems=problems[:200])
        if problems:
            raise DryRunFailed(problems[:50] + ([f"... and {len(problems) - 50} more"] if len(problems) > 50 else []))

    def _health(self, role: str, device: Any) -> list[str]:
        if role == "robot":
            state = device.state()
            if state.emergency_stop:
                return ["robot: emergency stop engaged"]
            if state.protective_stop:
                return ["robot: in protective stop"]
            if not state.program_running:
                return ["robot: control program not running"]
        elif role == "rotary_table":
            state = device.state()
            if state.fault:
                return [f"rotary table: fault {state.fault}"]
        elif role == "interferometer":
            pass  # its beam is only meaningful once aligned; checked by the first reading
        return []

    def _robot_speed(self) -> tuple[float, float]:
        envelope = self.station.envelope
        return (envelope.max_speed * self.params.speed_percent / 100.0,
                envelope.max_acceleration * self.params.acceleration_percent / 100.0)

    # ------------------------------------------------------------------------------- pausing
    def _safe_point(self) -> None:
        self._check_abort()
        if self._pause_request.is_set():
            self._pause(self._pause_reason)

    def _pause(self, reason: str) -> None:
        self._pause_request.clear()
        self._resume_request.clear()
        self._set_state("PAUSED", reason=reason, hook="run_paused")
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
        self._set_state("RUNNING", reason="resumed", hook="run_resumed")

    # ---------------------------------------------------------------------------------- steps
    def _ensure_setup(self, required: str) -> None:
        current, operator = self._setup, self.station.operator
        if current == required:
            return
        if required == "robot":
            if current is not None and current.startswith("table:"):
                operator.mount_opr("robot")
        elif required.startswith("align:"):
            if current is not None and current.startswith("table:"):
                operator.mount_opr("robot")
            operator.align_interferometer(required.split(":")[1])
        elif required.startswith("table:"):
            operator.mount_opr(required)
            if isinstance(self.procedure, AngleCalibration) and self.params.home_table and not self._table_homed:
                if not self.station.table.state().homed:
                    self.station.table.home(timeout=self.params.move_timeout_s)
                self._table_homed = True
        self.store.log(self.run_id, "setup", required)
        self._emit("setup", setup=required)
        self._setup = required

    def _do_step(self, step: Step) -> bool:
        t_start = time.time()
        # The interferometer is aimed at the reflector where it stands, so a new alignment waits
        # until the robot has brought the OPR to the first point of the line.
        aligning = step.setup.startswith("align:") and self._setup != step.setup
        if not aligning:
            self._ensure_setup(step.setup)
        self._check_abort()
        reference: dict[str, Any] = {}
        if step.tcp_pose is not None:
            speed, acceleration = self._robot_speed()
            self.station.robot.move_linear(np.asarray(step.tcp_pose), speed, acceleration,
                                           timeout=self.params.move_timeout_s)
        if aligning:
            self._ensure_setup(step.setup)
        if step.table_angle is not None:
            table = self.station.table
            table.move_absolute(step.table_angle, speed=np.radians(self.params.table_speed_deg_s))
            table.wait_in_position(timeout=self.params.move_timeout_s)
        self._wait(self.params.settle_time_s)
        if step.table_angle is not None:
            reference["table_rad"] = float(self.station.table.position())
            reference["value"] = reference["table_rad"]
        if isinstance(self.procedure, DisplacementCalibration):
            interferometer = self.station.interferometer
            if step.meta.get("zero_interferometer"):
                interferometer.zero()
            duration = self.params.interferometer_average_s
            reading = float(interferometer.average(duration, timeout=duration + 10.0))
            reference.update(interferometer_m=reading, value=step.meta["group_start"] + reading)
        if step.tcp_pose is not None:
            reference["robot_tcp_pose"] = [float(v) for v in self.station.robot.tcp_pose()]
        self._check_abort()
        result = self._measure(step)
        commanded = {"tcp_pose": step.tcp_pose, "table_angle": step.table_angle, "nominal": step.meta.get("nominal")}
        self.store.add_sample(
            self.run_id, step.index, step.key, step.phase, label=step.label, ok=result["ok"], error=result.get("error"),
            commanded=commanded, solved=result.get("solved"), corrected=result.get("corrected"),
            crosses=result.get("crosses"), reference=reference, meta=step.meta, frames=result.get("frames"),
            t_start=t_start, t_measured=result.get("t_measured"),
        )
        # Committed: from here on nothing can lose this sample.
        self._durations.append(time.time() - t_start)
        pose = (result.get("corrected") or result.get("solved") or {}).get("pose")
        event = self._emit("point_measured", step=step.index, key=step.key, label=step.label, ok=result["ok"],
                           error=result.get("error"), pose=pose,
                           residual_rms=(result.get("solved") or {}).get("residual_rms"),
                           reference=reference.get("value"))
        self.hooks.emit(event)
        self._emit_progress(step)
        return result["ok"]

    def _emit_progress(self, step: Step) -> None:
        done = len(self.store.committed_steps(self.run_id))
        total = len(self.plan)
        recent = self._durations[-20:]
        eta = float(np.mean(recent)) * (total - done) if recent else None
        self._emit("progress", done=done, total=total, eta_s=eta, step=step.index, label=step.label)

    def _measure(self, step: Step) -> dict[str, Any]:
        p = self.params
        last_error, frames_saved = "", []
        for attempt in range(p.retries_per_pose + 1):
            self._check_abort()
            triples: list[dict[str, Any]] = []
            try:
                for _ in range(p.frames_per_pose):
                    triples.append({s: self.station.camera(s).grab(timeout=p.grab_timeout_s) for s in SCREENS})
                measurements = [self.science.measure(triple) for triple in triples]
            except (MeasurementFailed, GrabFailed) as exc:
                last_error = f"attempt {attempt + 1}: {exc}"
                self.store.log(self.run_id, "measure_failed", f"{step.key}: {last_error}")
                if p.save_frames != "never":
                    frames_saved += self._save_frames(step, triples, f"failed{attempt}")
                continue
            poses = np.array([m.pose for m in measurements])
            solved = {
                "pose": poses.mean(axis=0).tolist(),
                "pose_std": poses.std(axis=0).tolist(),
                "per_frame": poses.tolist(),
                "residual_rms": float(np.mean([m.residual_rms for m in measurements])),
                "components": list(COMPONENTS),
            }
            corrected = None
            if self.compensators:
                pose, flags = np.asarray(solved["pose"]), []
                for compensator in self.compensators:
                    pose, more = compensator.correct(pose)
                    flags += list(more)
                corrected = {"pose": [float(v) for v in pose], "flags": flags,
                             "records": [c.record_id for c in self.compensators]}
            if p.save_frames == "always":
                frames_saved += self._save_frames(step, triples, "ok")
            stamps = [f.timestamp for t in triples for f in t.values()]
            return {"ok": True, "solved": solved, "corrected": corrected, "frames": frames_saved or None,
                    "crosses": {s: [m.crosses.get(s) for m in measurements] for s in SCREENS},
                    "t_measured": float(np.mean(stamps)), "attempts": attempt + 1}
        return {"ok": False, "error": last_error, "frames": frames_saved or None}

    def _save_frames(self, step: Step, triples: list[dict[str, Any]], tag: str) -> list[str]:
        folder = self.store.run_dir(self.run_id) / "frames"
        folder.mkdir(exist_ok=True)
        stem = f"{step.index:05d}_{re.sub(r'[^A-Za-z0-9]+', '-', step.key)}_{tag}"
        saved = []
        for number, triple in enumerate(triples):
            for screen, frame in triple.items():
                path = folder / f"{stem}_{number}_{screen}.npy"
                np.save(path, np.asarray(frame.image))
                saved.append(str(Path("frames") / path.name))
        return saved
