"""The controller core of the UR twin: joints, motions, safety state, RTDE registers, repeatability.

What the controller reports and what is true
--------------------------------------------
A real UR reports ``actual_q`` from its joint encoders and ``actual_TCP_pose`` as the forward
kinematics of those joints through its nominal model. The causes of pose repeatability error —
joint and gear elasticity, backlash on the output side of the encoders, thermal growth of the links —
are invisible to those encoders. So this twin reports, at rest, exactly the commanded pose (encoder
readings equal the commanded joints), while the TRUE attained pose, ``commanded ⊕ error``, goes only
to the world (``World.set_flange_pose``) and to ``visits`` for tests. The error of one visit is:

- a seeded normal error per base axis, σ = ``repeatability_translation_std`` (position) and
  ``repeatability_rotation_std`` (a small rotation vector, left-multiplied);
- ``approach_bias`` × the unit TCP displacement of the move (the same for every visit from the same
  side, like backlash);
- a warm-up drift ``A (1 − exp(−t/τ))`` along a seeded base direction (``t`` = simulated time).

During a move the world receives the commanded flange pose (``settled=False``) every
``world_publish_period``; when the move ends the attained pose is sent with ``settled=True`` BEFORE
the script signals completion, so a client told "done" can rely on every world subscriber having
seen the final pose.
"""

from __future__ import annotations

import threading
import time
import zlib
from collections.abc import Callable
from typing import Any

import numpy as np

from sim_devices._transforms import (
    invert,
    make_transform,
    matrix_to_pose6,
    matrix_to_rotvec,
    pose6_to_matrix,
    rotvec_to_matrix,
)
from sim_devices.faults import FaultKind, FaultPlan
from sim_devices.ur import _kinematics as kin
from sim_devices.ur._config import URTwinConfig
from sim_devices.ur._motion import Motion

# RTDE enumerations (UR RTDE guide).
RUNTIME_STOPPED, RUNTIME_PLAYING = 1, 2
ROBOT_MODE_POWER_OFF, ROBOT_MODE_RUNNING = 3, 7
SAFETY_MODE_NORMAL, SAFETY_MODE_PROTECTIVE_STOP, SAFETY_MODE_ROBOT_EMERGENCY_STOP = 1, 3, 7
SAFETY_BIT_NORMAL, SAFETY_BIT_PROTECTIVE, SAFETY_BIT_ROBOT_ESTOP, SAFETY_BIT_ESTOP = 1 << 0, 1 << 2, 1 << 6, 1 << 7
SAFETY_BIT_STOPPED_DUE_TO_SAFETY = 1 << 10
JOINT_RUNNING_MODE = 253
MID_MOVE_FAULTS = (FaultKind.PROTECTIVE_STOP, FaultKind.EMERGENCY_STOP, FaultKind.PROGRAM_STOPPED,
                   FaultKind.DISCONNECT)


class URController:
    """Joint state, motion, safety and register file of one simulated UR controller.

    Thread-safe: every mutation happens under ``self.lock``; ``self.changed`` (a condition on that
    lock) is notified on every input-register write, motion end and program stop.
    """

    def __init__(self, world, config: URTwinConfig, faults: FaultPlan,
                 on_disconnect: Callable[[], None] | None = None) -> None:
        self.world = world
        self.config = config
        self.faults = faults
        self.on_disconnect = on_disconnect or (lambda: None)
        self.lock = threading.RLock()
        self.changed = threading.Condition(self.lock)
        self._wall0 = time.monotonic()
        self._rng = np.random.default_rng([config.seed, zlib.crc32(b"ur-repeatability")])
        drift = np.random.default_rng([config.seed, zlib.crc32(b"ur-thermal-drift")]).normal(size=3)
        self._drift_direction = drift / np.linalg.norm(drift)

        self.tcp_offset = np.asarray(config.tcp_offset, dtype=float).copy()
        flange = world.flange_pose()
        self.q = kin.inverse(flange, kin.HOME_SEED)  # encoders start where the world says the flange is
        self.qd = np.zeros(6)
        self.tcp_pose = kin.forward(self.q, self.tcp_offset)
        self.tcp_speed = np.zeros(6)
        self.motion: Motion | None = None
        self._motion_callbacks: list[Callable[[Motion | None], None]] = []
        self._steady_since = 0.0
        self._last_publish = 0.0
        self._last_tick_t = 0.0

        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.in_int = [0] * 48
        self.in_double = [0.0] * 48
        self.input_seq = 0
        self.runtime_state = RUNTIME_STOPPED
        self.robot_mode = ROBOT_MODE_RUNNING
        self.safety_mode = SAFETY_MODE_NORMAL
        self.safety_bits = SAFETY_BIT_NORMAL
        self.stream_stall_until = 0.0
        self.program = None  # the running ControlScript, if any
        self.visits: list[dict[str, Any]] = []  # every settled attained pose (truth, for tests)
        self.events: list[str] = []  # what the controller did that a log would show
        self.snapshot: dict[str, Any] = {}
        self._update_snapshot(0.0)

        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ur-controller", daemon=True)

    # ----------------------------------------------------------------------------- lifecycle
    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        with self.changed:
            if self.program is not None:
                self.program.alive = False
            self.changed.notify_all()
        self._thread.join(2.0)

    def sim_time(self) -> float:
        return (time.monotonic() - self._wall0) * self.config.time_scale

    def log(self, message: str) -> None:
        with self.lock:
            self.events.append(f"{self.sim_time():.3f} {message}")
            del self.events[:-500]

    # ----------------------------------------------------------------------------- registers
    def set_inputs(self, values: dict[str, Any]) -> None:
        """Apply an RTDE input data package (only register fields matter to the twin)."""
        with self.changed:
            for name, value in values.items():
                if name.startswith("input_int_register_"):
                    self.in_int[int(name.rsplit("_", 1)[1])] = int(value)
                elif name.startswith("input_double_register_"):
                    self.in_double[int(name.rsplit("_", 1)[1])] = float(value)
            self.input_seq += 1
            self.changed.notify_all()

    # ----------------------------------------------------------------------------- motion API
    @property
    def moving(self) -> bool:
        return self.motion is not None

    def is_steady(self) -> bool:
        with self.lock:
            return self.motion is None and self.sim_time() - self._steady_since >= 0.05

    def start_motion(self, motion_factory: Callable[[float, np.ndarray, np.ndarray], Motion],
                     on_done: Callable[[Motion | None], None] | None = None) -> Motion:
        """Replace any running motion by a new one starting at the current commanded state."""
        with self.changed:
            if self.safety_bits & (SAFETY_BIT_PROTECTIVE | SAFETY_BIT_ESTOP):
                raise RuntimeError("motion refused: the robot is stopped by its safety system")
            t = self.sim_time()
            if self.motion is not None:
                self._sample(self.motion, t)
            self.motion = motion_factory(t, self.q.copy(), self.tcp_offset.copy())
            self._motion_callbacks = [on_done] if on_done else []
            self.changed.notify_all()
            return self.motion

    def detach_callbacks(self) -> None:
        with self.lock:
            self._motion_callbacks = []

    def stop_motion(self, deceleration: float,
                    on_done: Callable[[Motion | None], None] | None = None) -> Motion | None:
        """Decelerate the running motion to rest; ``on_done`` runs when it is at rest (at once if idle)."""
        with self.changed:
            motion = self.motion
            if motion is None:
                if on_done:
                    on_done(None)
                return None
            t = self.sim_time()
            motion.stop(t, deceleration if deceleration > 0 else self.config.stop_deceleration)
            if on_done:
                self._motion_callbacks.append(on_done)
            self.changed.notify_all()
            return motion

    def wait_motion(self, motion: Motion, alive: Callable[[], bool]) -> bool:
        """Block until ``motion`` is over (True) or ``alive()`` turns False (False)."""
        with self.changed:
            while self.motion is motion:
                if not alive() or self._stop.is_set():
                    return False
                self.changed.wait(0.05)
            return True

    def set_tcp(self, offset) -> None:
        with self.lock:
            self.tcp_offset = np.asarray(offset, dtype=float).reshape(6).copy()
            self.tcp_pose = kin.forward(self.q, self.tcp_offset)
            self.log(f"set_tcp {np.round(self.tcp_offset, 6).tolist()}")
            self._update_snapshot(self.sim_time())

    # ----------------------------------------------------------------------------- safety / program
    def protective_stop(self, reason: str = "protective stop", at_time: float | None = None) -> None:
        self._safety_stop(SAFETY_MODE_PROTECTIVE_STOP, SAFETY_BIT_PROTECTIVE | SAFETY_BIT_STOPPED_DUE_TO_SAFETY,
                          reason, at_time)

    def emergency_stop(self, reason: str = "emergency stop", at_time: float | None = None) -> None:
        self._safety_stop(SAFETY_MODE_ROBOT_EMERGENCY_STOP,
                          SAFETY_BIT_ROBOT_ESTOP | SAFETY_BIT_ESTOP | SAFETY_BIT_STOPPED_DUE_TO_SAFETY, reason, at_time)
        with self.lock:
            self.robot_mode = ROBOT_MODE_POWER_OFF

    def _safety_stop(self, mode: int, bits: int, reason: str, at_time: float | None = None) -> None:
        with self.changed:
            self.safety_mode = mode
            self.safety_bits = bits
            self.log(reason)
            if self.motion is not None:
                self.motion.stop(self.sim_time() if at_time is None else at_time, self.config.stop_deceleration)
            self.stop_program(reason)

    def clear_safety(self) -> None:
        """Unlock a protective stop / release an emergency stop (the program stays stopped)."""
        with self.changed:
            self.safety_mode = SAFETY_MODE_NORMAL
            self.safety_bits = SAFETY_BIT_NORMAL
            self.robot_mode = ROBOT_MODE_RUNNING
            self.log("safety cleared")
            self.changed.notify_all()

    def stop_program(self, reason: str) -> None:
        """Stop the running program (dashboard ``stop``, a fault, script end). Motion halts."""
        with self.changed:
            program = self.program
            if program is not None:
                program.alive = False
                self.program = None
                self.log(f"program stopped: {reason}")
            if self.motion is not None and not self.motion.stopped:
                self.motion.stop(self.sim_time(), self.config.stop_deceleration)
            self.runtime_state = RUNTIME_STOPPED
            self.changed.notify_all()

    def start_program(self, program) -> None:
        with self.changed:
            if self.program is not None:
                self.stop_program("replaced by a new program")
            self.program = program
            self.runtime_state = RUNTIME_PLAYING
            self.changed.notify_all()

    # ----------------------------------------------------------------------------- tick
    def _run(self) -> None:
        period = self.config.control_period
        while not self._stop.is_set():
            try:
                self.tick()
            except Exception as exc:  # never let the controller thread die silently
                self.log(f"controller tick failed: {type(exc).__name__}: {exc}")
            self._stop.wait(period)

    def tick(self) -> None:
        with self.changed:
            t = self.sim_time()
            motion = self.motion
            if motion is not None:
                self._sample(motion, t)
                self._mid_move_faults(motion, t)
                if self.motion is motion and t >= motion.t_end:
                    self._finish_motion(motion, t)
                elif (
                    self.motion is motion and time.monotonic() - self._last_publish >= self.config.world_publish_period
                ):
                    self._last_publish = time.monotonic()
                    self.world.set_flange_pose(kin.flange_from_tcp(self.tcp_pose, self.tcp_offset), settled=False,
                                               source="robot")
            else:
                self.qd = np.zeros(6)
                self.tcp_speed = np.zeros(6)
            self._update_snapshot(t)

    def _sample(self, motion: Motion, t: float) -> None:
        """Advance the commanded state along ``motion`` (the running one) to simulated time ``t``."""
        q, pose = motion.sample(t)
        dt = t - self._last_tick_t
        if dt > 0:
            self.qd = (q - self.q) / dt
            dp = (pose[:3, 3] - self.tcp_pose[:3, 3]) / dt
            dr = matrix_to_rotvec(pose[:3, :3] @ self.tcp_pose[:3, :3].T) / dt
            self.tcp_speed = np.concatenate([dp, dr])
        self._last_tick_t = t
        self.q, self.tcp_pose = q, pose

    def _mid_move_faults(self, motion: Motion, t: float) -> None:
        armed = self.faults.peek(*MID_MOVE_FAULTS)
        at = float(armed.params.get("at", 0.5)) if armed is not None else 1.0
        if armed is None or motion.stopped or motion.fraction(t) < at:
            return
        self.faults.take(armed.kind)
        # A late tick (loaded machine, high time scale) must not move the fault: it happens at the
        # simulated instant the path crossed ``at``.
        self.trigger(armed.kind, at_time=motion.time_at_fraction(at))
        if self.motion is motion:
            self._sample(motion, t)

    def trigger(self, kind: FaultKind | str, at_time: float | None = None) -> None:
        """Make a fault happen now (or, for a safety stop, at simulated time ``at_time``)."""
        kind = FaultKind(kind)
        if kind is FaultKind.PROTECTIVE_STOP:
            self.protective_stop("protective stop (injected)", at_time)
        elif kind is FaultKind.EMERGENCY_STOP:
            self.emergency_stop("emergency stop (injected)", at_time)
        elif kind is FaultKind.PROGRAM_STOPPED:
            self.stop_program("program stopped (injected)")
        elif kind is FaultKind.DISCONNECT:
            self.log("connections dropped (injected)")
            threading.Thread(target=self.on_disconnect, daemon=True).start()
        else:
            raise ValueError(f"fault {kind.value!r} cannot be triggered on the robot controller")

    def _finish_motion(self, motion: Motion, t: float) -> None:
        """At rest: draw the attained pose, tell the world (settled) FIRST, then the waiters."""
        commanded = self.tcp_pose.copy()
        attained = self._attained_pose(commanded, motion.start_pose, t)
        flange = kin.flange_from_tcp(attained, self.tcp_offset)
        self.world.set_flange_pose(flange, settled=True, source="robot")
        self.visits.append({
            "time": t,
            "commanded_tcp": matrix_to_pose6(commanded).tolist(),
            "attained_tcp": matrix_to_pose6(attained).tolist(),
            "attained_flange": matrix_to_pose6(flange).tolist(),
            "tcp_offset": self.tcp_offset.tolist(),
            "stopped": motion.stopped,
        })
        del self.visits[:-10_000]
        self.motion = None
        self.qd = np.zeros(6)
        self.tcp_speed = np.zeros(6)
        self._steady_since = t
        callbacks, self._motion_callbacks = self._motion_callbacks, []
        for callback in callbacks:
            callback(motion)
        self.changed.notify_all()

    def _attained_pose(self, commanded: np.ndarray, start: np.ndarray, t: float) -> np.ndarray:
        cfg = self.config
        approach = commanded[:3, 3] - start[:3, 3]
        norm = float(np.linalg.norm(approach))
        direction = approach / norm if norm > 1e-9 else np.zeros(3)
        drift = cfg.thermal_drift_amplitude * (1.0 - np.exp(-t / max(cfg.thermal_drift_time_constant, 1e-9)))
        position = (commanded[:3, 3] + self._rng.normal(0.0, cfg.repeatability_translation_std, 3)
                    + cfg.approach_bias * direction + drift * self._drift_direction)
        rotation = rotvec_to_matrix(self._rng.normal(0.0, cfg.repeatability_rotation_std, 3)) @ commanded[:3, :3]
        return make_transform(rotation, position)

    # ----------------------------------------------------------------------------- RTDE view
    def _update_snapshot(self, t: float) -> None:
        pose = matrix_to_pose6(self.tcp_pose).tolist()
        q = self.q.tolist()
        frames = kin.joint_frames(self.q)
        program_running = self.runtime_state == RUNTIME_PLAYING
        self.snapshot = {
            "timestamp": t,
            "target_q": q, "actual_q": q,
            "target_qd": self.qd.tolist(), "actual_qd": self.qd.tolist(),
            "actual_TCP_pose": pose, "target_TCP_pose": pose,
            "actual_TCP_speed": self.tcp_speed.tolist(), "target_TCP_speed": self.tcp_speed.tolist(),
            "robot_mode": self.robot_mode,
            "safety_mode": self.safety_mode, "safety_status": self.safety_mode,
            "safety_status_bits": self.safety_bits,
            "runtime_state": self.runtime_state,
            "robot_status_bits": 1 | (2 if program_running else 0) if self.robot_mode == ROBOT_MODE_RUNNING else 0,
            "joint_mode": [JOINT_RUNNING_MODE] * 6,
            "joint_temperatures": [31.0, 32.5, 32.0, 34.0, 35.0, 35.5],
            "actual_main_voltage": 48.0, "actual_robot_voltage": 48.0, "actual_robot_current": 0.6,
            "actual_joint_voltage": [47.8] * 6,
            "actual_tool_accelerometer": [0.0, 0.0, -9.81],
            "speed_scaling": 1.0, "target_speed_fraction": 1.0,
            "actual_execution_time": 0.25,
            "elbow_position": frames[3][:3, 3].tolist(),
            "elbow_velocity": [0.0, 0.0, 0.0],
            "payload": 0.0, "payload_cog": [0.0, 0.0, 0.0],
            "tcp_force_scalar": 0.0,
        }

    def describe(self) -> dict[str, Any]:
        with self.lock:
            return {
                "time": self.sim_time(),
                "q": self.q.tolist(),
                "tcp_pose": matrix_to_pose6(self.tcp_pose).tolist(),
                "tcp_offset": self.tcp_offset.tolist(),
                "flange_pose": matrix_to_pose6(self.tcp_pose @ invert(pose6_to_matrix(self.tcp_offset))).tolist(),
                "moving": self.motion is not None,
                "runtime_state": self.runtime_state,
                "robot_mode": self.robot_mode,
                "safety_mode": self.safety_mode,
                "safety_status_bits": self.safety_bits,
                "program": getattr(self.program, "name", None),
            }
