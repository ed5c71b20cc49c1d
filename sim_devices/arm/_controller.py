"""The controller core of the robot twins: one fixed cycle, joints, servos, motions, safety, registers.

Written for the UR twin (its cycle report uses RTDE field names as its vocabulary, and its register
file is RTDE's); the ABB twin runs the same core with its own arm and reads the fields it needs.

The cycle
---------
One thread runs the controller on a fixed grid of ``control_period`` (2 ms) wall seconds. Cycle
``k`` advances everything to controller time ``k · period`` (the RTDE ``timestamp``: seconds since
the controller started) and simulated time ``k · period · time_scale`` (motion), builds ONE
immutable ``CycleState`` (joints, poses, speeds, currents, modes, a copy of every register) and
hands it to the RTDE streams, which pack each client's recipe from it. A late cycle does not skip
its slot: the thread steps and sends every slot it missed, back to back (up to ``MAX_CATCH_UP``
slots, 1 s). A longer stall resynchronises and is counted in ``skipped_cycles``: its slots are not
sent, but the arm's physics is still advanced through them in steps of about 10 ms of simulated time
(a real arm does not stop while a host sleeps; one step across the gap would feed the servos a chord's
velocity and leave them ringing tens of µm off the path). Every lag of ``STALL_CYCLES`` (50 ms) or more
is counted in ``stalls``: the other twins saw the arm frozen that long, which a real cell never shows.

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
- a warm-up drift ``A (1 − exp(−t/τ))`` along a seeded base direction (``t`` = simulated time of the
  end of the move's profile).

During a move ``actual`` follows ``target`` through the joint servos (``_servo.py``): it lags by
``following_lag × speed`` and rings down after the profile ends. The move is over once that
residual is below ``settle_tolerance`` (``actual`` is then exactly ``target``). Then, off the
cycle thread, the attained flange pose goes to the world with ``settled=True`` (which returns once
every subscriber, in any process of the cell, has seen it), and only then, at least two cycles
after the final pose was first streamed (``DONE_AFTER_CYCLES``), the script is told the move is done. So a client told
"done" reads the final pose on any RTDE connection and every twin has seen the attained pose.
When a move is planned, its attained flange pose is announced to the world (``World.announce``),
so the camera twin can render the final frames while the arm is still moving.

The TRUE tool pose (``_dynamics``) adds what the encoders cannot see to the encoder pose: the
structural modes (a lag and sag during motion, a residual vibration after it) and the visit's
static error, blended in along the move. It is sampled at ``truth_rate`` in the cycle thread and
written per move to a trajectory record (``_trajectory``, ``sim_devices.trajectory``). The world
gets the true pose while the arm moves and, once the encoders have settled, the attained pose the
structure settles onto; the ring-down around it after "done" is in the trajectory record only.
"""

from __future__ import annotations

import math
import threading
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
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
from sim_devices.arm._dynamics import Structure, TruthGrid, matrix_to_quaternion_batch, rotvec_to_matrix_batch
from sim_devices.arm._kinematics import SerialArm
from sim_devices.arm._motion import Motion
from sim_devices.arm._servo import JointServos
from sim_devices.arm._trajectory import TrajectoryRecorder
from sim_devices.faults import FaultKind, FaultPlan
from sim_devices.world import session_seed

# RTDE enumerations (UR RTDE guide).
RUNTIME_STOPPED, RUNTIME_PLAYING = 1, 2
ROBOT_MODE_POWER_OFF, ROBOT_MODE_RUNNING = 3, 7
SAFETY_MODE_NORMAL, SAFETY_MODE_PROTECTIVE_STOP, SAFETY_MODE_ROBOT_EMERGENCY_STOP = 1, 3, 7
SAFETY_BIT_NORMAL, SAFETY_BIT_PROTECTIVE, SAFETY_BIT_ROBOT_ESTOP, SAFETY_BIT_ESTOP = 1 << 0, 1 << 2, 1 << 6, 1 << 7
SAFETY_BIT_STOPPED_DUE_TO_SAFETY = 1 << 10
JOINT_RUNNING_MODE = 253
MID_MOVE_FAULTS = (FaultKind.PROTECTIVE_STOP, FaultKind.EMERGENCY_STOP, FaultKind.PROGRAM_STOPPED,
                   FaultKind.DISCONNECT)
# Slots a late cycle thread makes up for (1 s); beyond that it resynchronises: the slots are not sent,
# and the physics goes through the gap (``_advance_through_stall``). A loaded host delays a cycle by far
# less, but repeatedly: it must catch up.
MAX_CATCH_UP = 500
# A cycle this many slots (50 ms) late is counted as a stall: the other twins saw the arm frozen that long.
STALL_CYCLES = 25
# Through a longer stall the physics advances in steps of about this many simulated seconds, and at most
# RESYNC_MAX_STEPS of them (a stall of minutes must not cost the cycle thread seconds of CPU).
RESYNC_STEP = 0.01
RESYNC_MAX_STEPS = 400
# At rest, with no listener that needs every cycle (no RTDE connection), the cycle thread wakes this
# often (s) and reports one cycle for the slots since (nothing moves, nobody reads them): an idle cell's
# robot twin cost an eighth of a core at 500 wake-ups a second.
QUIET_PERIOD = 0.02
# The true tool is computed for this many cycles at once (20 ms), in one vectorised step: per cycle, the
# numpy calls on two samples cost most of a cycle's 2 ms on a slow host, and a late cycle stalls the arm.
TRUTH_BATCH = 10
DONE_AFTER_CYCLES = 2  # "done" goes out this many cycles (4 ms) after the final pose was first streamed

# A coarse UR5e mass model for the joint currents: link masses (kg) at the middle of each link,
# torque constants (N·m/A, gear included) and reflected inertias (kg·m²) per joint.
LINK_MASSES = np.array([3.761, 8.058, 2.846, 1.37, 1.3, 0.365])
TORQUE_CONSTANTS = np.array([12.0, 12.0, 12.0, 9.0, 9.0, 9.0])
JOINT_INERTIAS = np.array([2.0, 2.0, 0.6, 0.1, 0.1, 0.05])
GRAVITY = np.array([0.0, 0.0, -9.81])
CURRENT_NOISE = 0.015  # A, per joint and cycle
FORCE_NOISE = (0.4, 0.02)  # N and N·m: the force estimate's noise with nothing in contact
NOISE_SCALE = np.array([CURRENT_NOISE] * 6 + [FORCE_NOISE[0]] * 3 + [FORCE_NOISE[1]] * 3)
NOISE_BLOCK = 500  # cycles of sensor noise drawn at once


@dataclass(frozen=True)
class CycleState:
    """Everything the controller reports in one cycle (RTDE field names), from one state."""

    cycle: int
    fields: dict[str, Any]


@dataclass
class MoveRun:
    """A motion being executed: its profile, what it will attain, and who waits for it."""

    motion: Motion
    tcp_offset: np.ndarray
    noise: tuple[np.ndarray, np.ndarray]  # the visit's random position and rotation-vector error
    planned_flange: np.ndarray  # attained flange pose if the profile runs to its end
    callbacks: list[Callable[[Motion | None], None]] = field(default_factory=list)
    phase: str = "moving"  # moving → settling → finishing (the finisher publishes it) → done
    end_cycle: int = 0
    settled_at: float = 0.0  # simulated time the servo residual fell below the tolerance
    done: threading.Event = field(default_factory=threading.Event)
    # The visit's static error (position, rotation vector), blended from the previous one along the move.
    error_from: tuple[np.ndarray, np.ndarray] = field(default_factory=lambda: (np.zeros(3), np.zeros(3)))
    error_to: tuple[np.ndarray, np.ndarray] = field(default_factory=lambda: (np.zeros(3), np.zeros(3)))
    progress: Callable[[int], None] | None = None  # told each time a path passes a waypoint
    waypoints_passed: int = 0
    record: int = 0  # its trajectory record's move number (0: none)


class ArmController:
    """Joint state, servos, motion, safety and register file of one simulated robot controller.

    Thread-safe: every mutation happens under ``self.lock``; ``self.changed`` (a condition on that
    lock) is notified on every input-register write, motion end and program stop. ``start()``
    runs the cycle; ``add_cycle_listener(fn)`` gets every ``CycleState`` (the RTDE streams of the UR
    twin, the EGM stream of the ABB twin).

    Parameters
    ----------
    world : World
        The cell's truth.
    config
        The twin's settings: any object with the physics fields of ``URTwinConfig`` (seed,
        time_scale, repeatability, servo, structure, truth, control_period ...).
    faults : FaultPlan
        Mid-move faults are taken from it.
    on_disconnect : callable, optional
        Called (on a thread of its own) when a ``disconnect`` fault fires.
    kinematics : SerialArm
        The arm.
    stream_label : str
        Names the seeded random streams (``"ur"``: the UR twin's draws, unchanged).
    """

    def __init__(self, world, config: Any, faults: FaultPlan, on_disconnect: Callable[[], None] | None = None, *,
                 kinematics: SerialArm, stream_label: str = "ur") -> None:
        self.kin = kinematics
        self.world = world
        self.config = config
        self.faults = faults
        self.on_disconnect = on_disconnect or (lambda: None)
        self.lock = threading.RLock()
        self.changed = threading.Condition(self.lock)
        self.period = float(config.control_period)
        session = world.config.session  # the noise is drawn anew in every session of the cell
        self._rng = np.random.default_rng(session_seed(config.seed, session, f"{stream_label}-repeatability"))
        drift_rng = np.random.default_rng([config.seed, zlib.crc32(f"{stream_label}-thermal-drift".encode())])
        drift = drift_rng.normal(size=3)
        self._drift_direction = drift / np.linalg.norm(drift)
        self._sensor_rng = np.random.default_rng(session_seed(config.seed, session, f"{stream_label}-sensors"))
        self._noise_block = np.zeros((0, 12))
        self._noise_next = 0
        self.servos = (JointServos(config.servo_frequency, config.servo_damping, config.following_lag,
                                   config.servo_frequency_spread,
                                   np.random.default_rng([config.seed, zlib.crc32(f"{stream_label}-servos".encode())]))
                       if config.servo_dynamics else None)

        self.tcp_offset = np.asarray(config.tcp_offset, dtype=float).copy()
        flange = world.flange_pose()
        # Commanded (target) state; encoders start where the world says the flange is.
        self.q = self.kin.inverse(flange, self.kin.home_seed)
        self.qd = np.zeros(6)
        self.qdd = np.zeros(6)
        self.tcp_pose = self.kin.forward(self.q, self.tcp_offset)
        self.tcp_speed = np.zeros(6)
        # Servo error of the actual joints against the target, and the actual TCP.
        self.error = np.zeros(6)
        self.error_rate = np.zeros(6)
        self.actual_tcp_pose = self.tcp_pose.copy()
        self.actual_tcp_speed = np.zeros(6)
        self.run: MoveRun | None = None
        self._steady_since = 0.0
        self._last_publish = 0.0
        # The truth beyond the encoders: structural modes, the static error, the dense record.
        self.truth_enabled = config.truth_rate > 0
        self.structure = (Structure(config.structure_frequencies, config.structure_dampings, config.structure_lag,
                                    config.structure_inertial_gain, config.structure_tilt_gain,
                                    config.structure_payload_reference)
                          if config.structure_dynamics and self.truth_enabled else None)
        self._grid = TruthGrid(self.tcp_pose)
        self.static_error = (np.zeros(3), np.zeros(3))  # of the last finished visit
        self._encoder_deviation = np.zeros(6)  # actual − target TCP: position, small rotation vector
        self.true_flange = flange.copy()
        # Cycles whose truth is still to be computed (``_queue_truth``), all of one kind (``_truth_key``).
        self._truth_pending: list[tuple[Any, ...]] = []
        self._truth_key: tuple[Any, ...] | None = None
        self._profile_ended = 0.0  # simulated time the last move's profile ended (for the record's tail)
        self.recorder = TrajectoryRecorder(config.trajectory_dir if self.truth_enabled else None,
                                           world.truth if self.truth_enabled else None,
                                           {"time_scale": config.time_scale, "control_period": self.period,
                                            "truth_rate": config.truth_rate})

        self.cycle = 0
        self.t_sim = 0.0
        self.skipped_cycles = 0
        self.late_cycles = 0
        self.stalls = 0  # times the cycle found itself STALL_CYCLES or more behind (the world froze that long)
        self.payload_mass = 0.0
        self.payload_cog = np.zeros(3)
        self.payload_inertia = np.zeros(6)
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.in_int = [0] * 48
        self.in_double = [0.0] * 48
        self.input_seq = 0
        # The newest input package a control script has acted on: a script started after another one
        # acts only on packages newer than that, so the stop command (255) that ended the previous script
        # is not taken again by the new one (a real controller takes far longer to start a program than
        # the client takes to clear the command register; the twin starts it within a cycle).
        self.handled_input_seq = -1
        self.runtime_state = RUNTIME_STOPPED
        self.robot_mode = ROBOT_MODE_RUNNING
        self.safety_mode = SAFETY_MODE_NORMAL
        self.safety_bits = SAFETY_BIT_NORMAL
        self.protective_stop_at: float | None = None  # wall (monotonic) time of the last protective stop
        self.stream_stall_until = 0.0
        self.program = None  # the running ControlScript, if any
        self.visits: list[dict[str, Any]] = []  # every settled attained pose (truth, for tests)
        self.events: list[str] = []  # what the controller did that a log would show
        self._listeners: list[Callable[[CycleState], None]] = []
        self._cycle_needs: list[Callable[[], bool] | None] = []  # per listener: does it need every cycle now?
        self._cycle_wake = threading.Event()  # ends a quiet wait at once (a motion starts)
        self._kinematic_fields: dict[str, Any] | None = None
        self._currents_now = np.zeros(6)
        self.current = self._cycle_state()

        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"{stream_label}-controller-cycle", daemon=True)
        self._finishing: list[MoveRun] = []
        self._finisher_wake = threading.Condition(threading.Lock())
        self._finisher = threading.Thread(target=self._finish_loop, name=f"{stream_label}-controller-finisher",
                                          daemon=True)

    # ----------------------------------------------------------------------------- lifecycle
    def start(self) -> None:
        self._wall0 = time.monotonic()
        self.recorder.write_clock({"monotonic_origin": self._wall0, "period": self.period,
                                   "time_scale": self.config.time_scale})
        self._thread.start()
        self._finisher.start()

    def stop(self) -> None:
        self._stop.set()
        with self.changed:
            if self.program is not None:
                self.program.alive = False
            self.changed.notify_all()
        with self._finisher_wake:
            self._finisher_wake.notify_all()
        for thread in (self._thread, self._finisher):
            if thread.is_alive():
                thread.join(2.0)
        with self.lock:
            self._flush_truth()
            self.recorder.close()

    def add_cycle_listener(self, listener: Callable[[CycleState], None],
                           needs_cycles: Callable[[], bool] | None = None) -> None:
        """``listener(state)`` on the cycle thread for every cycle (keep it short).

        ``needs_cycles()`` (cheap, any thread) says whether the listener needs every cycle now (the
        RTDE streams: while a client is connected); while no listener does and the arm rests, the
        cycle runs quiet (``QUIET_PERIOD``). Without it the listener always needs every cycle. A
        listener that starts needing cycles calls ``wake_cycle()``."""
        self._listeners.append(listener)
        self._cycle_needs.append(needs_cycles)

    def wake_cycle(self) -> None:
        """End a quiet wait now: a listener needs every cycle again."""
        self._cycle_wake.set()

    def sim_time(self) -> float:
        """Simulated seconds of the latest cycle."""
        return self.t_sim

    def log(self, message: str) -> None:
        with self.lock:
            self.events.append(f"{self.t_sim:.3f} {message}")
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
    def motion(self) -> Motion | None:
        """The motion being executed (until the finisher has reported it done)."""
        run = self.run
        return None if run is None else run.motion

    @property
    def moving(self) -> bool:
        return self.run is not None

    def is_steady(self) -> bool:
        with self.lock:
            return self.run is None and self.t_sim - self._steady_since >= 0.05

    def start_motion(self, motion_factory: Callable[[float, np.ndarray, np.ndarray], Motion],
                     on_done: Callable[[Motion | None], None] | None = None) -> Motion:
        """Replace any running motion by a new one starting at the current commanded state."""
        with self.changed:
            if self.safety_bits & (SAFETY_BIT_PROTECTIVE | SAFETY_BIT_ESTOP):
                raise RuntimeError("motion refused: the robot is stopped by its safety system")
            t = self.t_sim
            self._flush_truth()  # the cycles so far, with the run and the record they belong to
            error_from = self._static_error_now(t)
            if self.run is not None:
                self.run.phase = "replaced"
                self.run.done.set()
            motion = motion_factory(t, self.q.copy(), self.tcp_offset.copy())
            noise = (self._rng.normal(0.0, self.config.repeatability_translation_std, 3),
                     self._rng.normal(0.0, self.config.repeatability_rotation_std, 3))
            planned = self._attained_flange(motion.target_pose, motion.start_pose, motion.t_end, noise,
                                            self.tcp_offset)
            self.run = MoveRun(motion, self.tcp_offset.copy(), noise, planned, [on_done] if on_done else [],
                               error_from=error_from,
                               error_to=self._static_error(motion.target_pose, motion.start_pose, motion.t_end, noise))
            if self.truth_enabled:
                self.run.record = self.recorder.open({
                    "kind": motion.kind, "t_start": t / self.config.time_scale,
                    "tcp_offset": self.tcp_offset.tolist(), "start_tcp": matrix_to_pose6(motion.start_pose).tolist(),
                    "target_tcp": matrix_to_pose6(motion.target_pose).tolist(),
                    "attained_flange": matrix_to_pose6(planned).tolist(),
                    "payload": self.payload_mass})
            self.changed.notify_all()
        self._cycle_wake.set()
        self.world.announce(flange_pose=planned)  # the cameras may render the end pose meanwhile
        return motion

    def detach_callbacks(self) -> None:
        with self.lock:
            if self.run is not None:
                self.run.callbacks = []

    def stop_motion(self, deceleration: float,
                    on_done: Callable[[Motion | None], None] | None = None) -> Motion | None:
        """Decelerate the running motion to rest; ``on_done`` runs when it is at rest (at once if idle)."""
        with self.changed:
            run = self.run
            if run is None or run.done.is_set():
                if on_done:
                    on_done(None)
                return None
            if run.phase == "moving":
                run.motion.stop(self.t_sim, deceleration if deceleration > 0 else self.config.stop_deceleration)
            if on_done:
                run.callbacks.append(on_done)
            self.changed.notify_all()
            return run.motion

    def wait_motion(self, motion: Motion, alive: Callable[[], bool]) -> bool:
        """Block until ``motion`` is over and reported (True) or ``alive()`` turns False (False)."""
        with self.lock:
            run = self.run if self.run is not None and self.run.motion is motion else None
        if run is None:
            return True
        while not run.done.wait(0.05):
            if not alive() or self._stop.is_set():
                return False
        return True

    def set_tcp(self, offset) -> None:
        with self.lock:
            self._flush_truth()  # computed with the offset they were measured with
            self.tcp_offset = np.asarray(offset, dtype=float).reshape(6).copy()
            self.tcp_pose = self.kin.forward(self.q, self.tcp_offset)
            self.actual_tcp_pose = self.kin.forward(self.q + self.error, self.tcp_offset)
            self._kinematic_fields = None
            self.log(f"set_tcp {np.round(self.tcp_offset, 6).tolist()}")

    def set_payload(self, mass: float, cog: np.ndarray | None = None, inertia: np.ndarray | None = None) -> None:
        """``set_payload`` / ``set_target_payload``: a cog of all zeros keeps the current one (as the script)."""
        with self.lock:
            self._flush_truth()  # the structure's response so far with the payload it had
            self.payload_mass = float(mass)
            if cog is not None and np.any(np.asarray(cog) != 0):
                self.payload_cog = np.asarray(cog, dtype=float).reshape(3).copy()
            if inertia is not None:
                self.payload_inertia = np.asarray(inertia, dtype=float).reshape(6).copy()
            self._kinematic_fields = None
            if self.structure is not None:
                self.structure.set_payload(self.payload_mass)
            self.log(f"set_payload mass={self.payload_mass} cog={self.payload_cog.tolist()}")
            cog_now, inertia_now = self.payload_cog.tolist(), self.payload_inertia.tolist()
        self.world.truth.record("payload", time=self.world.clock(), mass=float(mass), cog=cog_now,
                                inertia=inertia_now)

    # ----------------------------------------------------------------------------- safety / program
    def protective_stop(self, reason: str = "protective stop", at_time: float | None = None) -> None:
        self._safety_stop(SAFETY_MODE_PROTECTIVE_STOP, SAFETY_BIT_PROTECTIVE | SAFETY_BIT_STOPPED_DUE_TO_SAFETY,
                          reason, at_time)
        with self.lock:
            self.protective_stop_at = time.monotonic()

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
            run = self.run
            if run is not None and run.phase == "moving":
                run.motion.stop(self.t_sim if at_time is None else at_time, self.config.stop_deceleration)
            self.stop_program(reason)

    def unlock_wait(self) -> float:
        """Seconds until a protective stop may be unlocked (0: now, or no protective stop)."""
        with self.lock:
            if not self.safety_bits & SAFETY_BIT_PROTECTIVE or self.protective_stop_at is None:
                return 0.0
            return max(0.0, self.protective_stop_at + self.config.protective_stop_unlock_delay - time.monotonic())

    def clear_safety(self) -> None:
        """Unlock a protective stop / release an emergency stop (the program stays stopped)."""
        with self.changed:
            self.safety_mode = SAFETY_MODE_NORMAL
            self.safety_bits = SAFETY_BIT_NORMAL
            self.robot_mode = ROBOT_MODE_RUNNING
            self.protective_stop_at = None
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
            run = self.run
            if run is not None and run.phase == "moving" and not run.motion.stopped:
                run.motion.stop(self.t_sim, self.config.stop_deceleration)
            self.runtime_state = RUNTIME_STOPPED
            self.changed.notify_all()

    def start_program(self, program) -> None:
        with self.changed:
            if self.program is not None:
                self.stop_program("replaced by a new program")
            self.program = program
            self.runtime_state = RUNTIME_PLAYING
            self.changed.notify_all()

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

    # ----------------------------------------------------------------------------- the cycle
    def _run(self) -> None:
        period = self.period
        slot = 0
        behind_before = 0
        while not self._stop.is_set():
            if self._quiet():
                self._cycle_wake.wait(QUIET_PERIOD)
                self._cycle_wake.clear()
                # Nothing moved and nobody read the slots since: the clock jumps to now, one report.
                slot = max(slot, int((time.monotonic() - self._wall0) / period))
                behind_before = 0
                self.step(slot)
                slot += 1
                continue
            due = self._wall0 + slot * period
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
                continue
            behind = int(-delay / period)
            if behind > MAX_CATCH_UP:  # a long stall (SIGSTOP, a frozen VM): resynchronise, and say so
                self.skipped_cycles += behind
                self.log(f"controller cycle resynchronised after {behind} missed cycles")
                self._advance_through_stall(slot, slot + behind)
                slot += behind
            elif behind > 0:
                self.late_cycles += 1
            if behind >= STALL_CYCLES > behind_before:
                self.stalls += 1  # once per stall, not per slot made up
            behind_before = behind
            try:
                self.step(slot)
            except Exception as exc:  # never let the controller die silently
                self.log(f"controller cycle failed: {type(exc).__name__}: {exc}")
            slot += 1
            if behind > 0:
                # Making up slots back to back would take the lock again at once, every time: let the
                # finisher (and the servers) have it between two of them, or a late cycle starves them.
                time.sleep(0)

    def _at_rest(self) -> bool:
        """No motion, no joint or servo residual moving, no trajectory record open: nothing to advance."""
        # ndarray.any() rather than np.any(): the check runs 500 times a second
        return (self.run is None and not self.qd.any() and not self.qdd.any() and not self.error.any()
                and not self.error_rate.any() and not self.recorder.is_open)

    def _quiet(self) -> bool:
        """At rest, nothing left to finish or compute, and no listener needs every cycle (the listeners
        first: while a client is connected that is the whole check, every cycle)."""
        return (not any(needs is None or needs() for needs in self._cycle_needs)
                and not self._finishing and not self._truth_pending and self._at_rest())

    def step(self, slot: int) -> CycleState:
        """Advance to cycle ``slot``, publish its state to the listeners; returns it."""
        publish = None
        with self.changed:
            self._physics_to(slot)
            now = time.monotonic()
            if (self.run is not None and self.run.phase in ("moving", "settling")
                    and now - self._last_publish >= self.config.world_publish_period):
                self._last_publish = now
                self._flush_truth()
                publish = (self.true_flange.copy() if self.truth_enabled
                           else self.kin.flange_from_tcp(self.actual_tcp_pose, self.tcp_offset))
            state = self.current = self._cycle_state()
        if publish is not None:
            self.world.set_flange_pose(publish, settled=False, source="robot")
        for listener in self._listeners:
            listener(state)
        return state

    def _physics_to(self, slot: int) -> None:
        """Joints, servos, motion and truth from the current cycle to cycle ``slot`` (lock held)."""
        t_prev = self.t_sim
        self.cycle = slot
        self.t_sim = t = slot * self.period * self.config.time_scale
        h = t - t_prev
        if h > 0 and not self._at_rest():
            self._advance(self.run, t, h)

    def _advance_through_stall(self, first: int, last: int) -> None:
        """The physics through slots ``first`` … ``last`` (excluded) of a stall, nothing published."""
        per_step = max(1, round(RESYNC_STEP / (self.period * self.config.time_scale)))
        stride = max(per_step, math.ceil((last - first) / RESYNC_MAX_STEPS))
        with self.changed:
            for slot in range(first, last, stride):
                self._physics_to(slot)

    def _advance(self, run: MoveRun | None, t: float, h: float) -> None:
        """Target along the motion, servo error, actual TCP: from the previous cycle to time ``t``."""
        if run is not None and run.phase == "moving":
            self._mid_move_faults(run, t)  # before sampling: a stop injected now changes the profile
            q, pose = run.motion.sample(t)
            if run.progress is not None:
                passed = run.motion.waypoints_passed(t)
                if passed != run.waypoints_passed:
                    run.waypoints_passed = passed
                    run.progress(passed)
            if t >= run.motion.t_end:
                run.phase = "settling"
                self._profile_ended = run.motion.t_end
        else:
            q, pose = self.q, self.tcp_pose
        qd = (q - self.q) / h
        self.qdd = (qd - self.qd) / h
        self.tcp_speed = _twist(self.tcp_pose, pose, h)
        self.qd = qd
        self.q, self.tcp_pose = q, pose
        if self.servos is not None:
            self.error, self.error_rate = self.servos.step(self.error, self.error_rate, self.qd, self.qdd, h)
        if run is not None and run.phase == "settling" and (
                self.servos is None or self.servos.settled(self.error, self.error_rate, self.config.settle_tolerance)):
            self.error = np.zeros(6)
            self.error_rate = np.zeros(6)
            self.qd = np.zeros(6)
            self.qdd = np.zeros(6)
            self.tcp_speed = np.zeros(6)
            run.phase = "finishing"
            run.end_cycle = self.cycle
            run.settled_at = t
            self._hand_to_finisher(run)
        actual = self.tcp_pose if not np.any(self.error) else self.kin.forward(self.q + self.error, self.tcp_offset)
        self.actual_tcp_speed = _twist(self.actual_tcp_pose, actual, h)
        self.actual_tcp_pose = actual
        if self.truth_enabled:
            deviation = np.zeros(6)
            if actual is not self.tcp_pose:
                deviation[:3] = actual[:3, 3] - self.tcp_pose[:3, 3]
                deviation[3:] = matrix_to_rotvec(actual[:3, :3] @ self.tcp_pose[:3, :3].T)
            self._queue_truth(run, t - h, t, self._encoder_deviation, deviation)
            self._encoder_deviation = deviation

    # ----------------------------------------------------------------------------- the truth
    def _static_error(self, commanded: np.ndarray, start: np.ndarray, t_end: float,
                      noise: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """The visit's static error (position offset, rotation vector) as ``_attained_flange`` applies it."""
        cfg = self.config
        approach = commanded[:3, 3] - start[:3, 3]
        norm = float(np.linalg.norm(approach))
        direction = approach / norm if norm > 1e-9 else np.zeros(3)
        drift = cfg.thermal_drift_amplitude * (1.0 - np.exp(-t_end / max(cfg.thermal_drift_time_constant, 1e-9)))
        return noise[0] + cfg.approach_bias * direction + drift * self._drift_direction, noise[1].copy()

    def _static_error_now(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        run = self.run
        if run is None or run.phase in ("done", "replaced"):
            return self.static_error
        u = run.motion.fraction(t)
        return (run.error_from[0] + u * (run.error_to[0] - run.error_from[0]),
                run.error_from[1] + u * (run.error_to[1] - run.error_from[1]))

    def _queue_truth(self, run: MoveRun | None, t_prev: float, t: float, deviation_prev: np.ndarray,
                     deviation: np.ndarray) -> None:
        """One cycle's truth, computed with the others of its kind (one move, one grid step) by
        ``_flush_truth``: after ``TRUTH_BATCH`` cycles, before the true pose is published, and before
        anything it depends on changes (a new move, the TCP offset, the payload)."""
        n = max(1, int(math.ceil((t - t_prev) * self.config.truth_rate - 1e-9)))
        active = run is not None and run.phase in ("moving", "settling", "finishing")
        key = (run if active else None, round((t - t_prev) / n, 12),
               None if active else (id(self.tcp_pose), id(self.static_error)))
        if self._truth_pending and key != self._truth_key:
            self._flush_truth()
        self._truth_key = key
        self._truth_pending.append((t_prev, t, n, deviation_prev, deviation, self.tcp_pose, self.static_error))
        if len(self._truth_pending) >= TRUTH_BATCH:
            self._flush_truth()

    def _flush_truth(self) -> None:
        """The true tool on the truth grid for the queued cycles: commanded pose, encoder deviation
        (interpolated between two cycles), structural deflection and static error; recorded."""
        pending, self._truth_pending = self._truth_pending, []
        if not pending:
            return
        assert self._truth_key is not None
        run = self._truth_key[0]
        times_list, dev_list = [], []
        for t_prev, t_end, count, deviation_prev, deviation, _, _ in pending:
            weights = np.arange(1, count + 1) / count
            times_list.append(t_prev + (t_end - t_prev) * weights)
            dev_list.append(deviation_prev + weights[:, None] * (deviation - deviation_prev))
        times, dev = np.concatenate(times_list), np.concatenate(dev_list)
        n = len(times)
        step = float(self._truth_key[1])
        t = pending[-1][1]
        if run is not None:
            poses, fractions = run.motion.poses_at(times)
            fraction = fractions[:, None]
            e_from, e_to = run.error_from, run.error_to
        else:
            poses = np.repeat(pending[0][5][None], n, axis=0)
            fraction = np.ones((n, 1))
            e_from = e_to = pending[0][6]
        positions, rotations = poses[:, :3, 3], poses[:, :3, :3]
        encoder_rotation = rotvec_to_matrix_batch(dev[:, 3:]) @ rotations
        encoder_position = positions + dev[:, :3]
        if self.structure is not None:
            velocity, acceleration = self._grid.derivatives(positions, rotations, step)
            deflection = self.structure.advance(self.structure.forcing(velocity, acceleration), step)
        else:
            deflection = np.zeros((n, 6))
        error_position = e_from[0] + fraction * (e_to[0] - e_from[0])
        error_rotation = e_from[1] + fraction * (e_to[1] - e_from[1])
        true_rotation = (rotvec_to_matrix_batch(deflection[:, 3:]) @ rotvec_to_matrix_batch(error_rotation)
                         @ encoder_rotation)
        true_position = encoder_position + error_position + deflection[:, :3]
        offset = pose6_to_matrix(self.tcp_offset)
        flange_rotation = true_rotation @ offset[:3, :3].T
        flange_position = true_position - flange_rotation @ offset[:3, 3]
        self.true_flange = make_transform(flange_rotation[-1], flange_position[-1])
        rows = np.column_stack([
            times / self.config.time_scale,
            flange_position, matrix_to_quaternion_batch(flange_rotation),
            positions, matrix_to_quaternion_batch(rotations),
            encoder_position, matrix_to_quaternion_batch(encoder_rotation)])
        self.recorder.append(rows)
        if (self.run is None and not np.any(self.error) and not np.any(self.error_rate) and self.recorder.is_open
                and (self.structure is None or self.structure.amplitude() < self.config.truth_tail_tolerance
                     or t - self._profile_ended > self.config.truth_tail_max)):
            self.recorder.close()
            if self.structure is not None:  # below a nanometre: the rest is the attained pose
                self.structure.deflection = np.zeros(6)
                self.structure.rate = np.zeros(6)

    def _mid_move_faults(self, run: MoveRun, t: float) -> bool:
        """Fire an armed mid-move fault once the path has crossed its fraction ``at``; True if one fired."""
        armed = self.faults.peek(*MID_MOVE_FAULTS)
        at = float(armed.params.get("at", 0.5)) if armed is not None else 1.0
        if armed is None or run.motion.stopped or run.motion.fraction(t) < at:
            return False
        self.faults.take(armed.kind)
        # A late cycle (loaded machine, high time scale) must not move the fault: it happens at the
        # simulated instant the path crossed ``at``.
        self.trigger(armed.kind, at_time=run.motion.time_at_fraction(at))
        return True

    # ----------------------------------------------------------------------------- finishing a move
    def _hand_to_finisher(self, run: MoveRun) -> None:
        with self._finisher_wake:
            self._finishing.append(run)
            self._finisher_wake.notify_all()

    def _finish_loop(self) -> None:
        while not self._stop.is_set():
            with self._finisher_wake:
                while not self._finishing and not self._stop.is_set():
                    self._finisher_wake.wait(0.2)
                if self._stop.is_set():
                    return
                run = self._finishing.pop(0)
            try:
                self._finish(run)
            except Exception as exc:
                self.log(f"finishing a move failed: {type(exc).__name__}: {exc}")
                run.done.set()

    def _finish(self, run: MoveRun) -> None:
        """At rest: the attained pose to the world (settled; every subscriber sees it), then done."""
        motion = run.motion
        with self.lock:
            if self.run is not run:  # replaced by a newer move meanwhile: nothing settled here
                run.done.set()
                return
            commanded = self.tcp_pose.copy()
        if not motion.stopped and np.array_equal(commanded, motion.target_pose):
            flange = run.planned_flange  # exactly what was announced: the cameras' early frames fit
        else:
            flange = self._attained_flange(commanded, motion.start_pose, motion.t_end, run.noise, run.tcp_offset)
        publishing = time.monotonic()
        self.world.set_flange_pose(flange, settled=True, source="robot")
        published_in = time.monotonic() - publishing  # until every twin of the cell had seen it
        attained = flange @ pose6_to_matrix(run.tcp_offset)
        with self.lock:
            self.visits.append({
                "time": motion.t_end,
                "commanded_tcp": matrix_to_pose6(commanded).tolist(),
                "attained_tcp": matrix_to_pose6(attained).tolist(),
                "attained_flange": matrix_to_pose6(flange).tolist(),
                "tcp_offset": run.tcp_offset.tolist(),
                "stopped": motion.stopped,
                "settling_time": run.settled_at - motion.t_end,
                "end_timestamp": run.end_cycle * self.period,  # RTDE timestamp of the first package at rest
                "publish_wait": published_in,  # wall s the settled pose took to reach every subscriber
                "move": run.record,  # its trajectory record
            })
            del self.visits[:-10_000]
        # The final pose has been streamed since ``end_cycle``; give every client a cycle or two to
        # read it before any connection is told the move is done.
        while self.cycle < run.end_cycle + DONE_AFTER_CYCLES and not self._stop.is_set():
            time.sleep(self.period / 2)
        with self.changed:
            if self.run is run:
                self.run = None
                self._steady_since = self.t_sim
                self.static_error = self._static_error(commanded, motion.start_pose, motion.t_end, run.noise)
            run.phase = "done"
            callbacks, run.callbacks = run.callbacks, []
            for callback in callbacks:
                callback(motion)
            # The next cycle's package is the first that can carry "done" (the registers written now).
            done_timestamp = (self.cycle + 1) * self.period
            self.visits[-1]["done_timestamp"] = done_timestamp
            if self.recorder.is_open and self.recorder.current is not None and \
                    self.recorder.current["move"] == run.record:
                self.recorder.note(done_timestamp=done_timestamp,
                                   profile_end=motion.t_end / self.config.time_scale,
                                   servo_settled=run.settled_at / self.config.time_scale,
                                   end_timestamp=run.end_cycle * self.period,
                                   attained_flange=matrix_to_pose6(flange).tolist(), stopped=motion.stopped)
            run.done.set()
            self.changed.notify_all()

    def _attained_flange(self, commanded: np.ndarray, start: np.ndarray, t_end: float,
                         noise: tuple[np.ndarray, np.ndarray], tcp_offset: np.ndarray) -> np.ndarray:
        cfg = self.config
        approach = commanded[:3, 3] - start[:3, 3]
        norm = float(np.linalg.norm(approach))
        direction = approach / norm if norm > 1e-9 else np.zeros(3)
        drift = cfg.thermal_drift_amplitude * (1.0 - np.exp(-t_end / max(cfg.thermal_drift_time_constant, 1e-9)))
        position = commanded[:3, 3] + noise[0] + cfg.approach_bias * direction + drift * self._drift_direction
        rotation = rotvec_to_matrix(noise[1]) @ commanded[:3, :3]
        return self.kin.flange_from_tcp(make_transform(rotation, position), tcp_offset)

    # ----------------------------------------------------------------------------- RTDE view
    def _currents(self, frames: list[np.ndarray], qdd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Joint torques (gravity of links and payload + inertia) and the currents they take."""
        origins = np.array([f[:3, 3] for f in frames])  # 0 = base … 6 = flange
        axes = np.array([f[:3, 2] for f in frames[:6]])  # joint i turns about z of frame i
        points = 0.5 * (origins[:-1] + origins[1:])  # link i's mass between frames i and i+1
        masses = LINK_MASSES.copy()
        points = np.vstack([points, frames[6][:3, :3] @ self.payload_cog + origins[6]])
        masses = np.append(masses, self.payload_mass)
        lever = points[None, :, :] - origins[:6, None, :]  # joint i → mass j
        # Gravity is along −z, so (lever × m·g) = m·g·(−lever_y, lever_x, 0), written out (np.cross is slow).
        weight = masses * GRAVITY[2]
        moments = np.stack([lever[..., 1] * weight, -lever[..., 0] * weight, np.zeros(lever.shape[:2])], axis=-1)
        outboard = np.arange(7)[None, :] >= np.arange(6)[:, None]  # masses beyond joint i
        gravity = -np.einsum("ijk,ik->ij", moments, axes)
        torque = np.sum(gravity * outboard, axis=1) + JOINT_INERTIAS * qdd
        return torque, torque / TORQUE_CONSTANTS

    def _cycle_state(self) -> CycleState:
        """This cycle's report: the kinematic part (recomputed only while something moves), the
        sensor noise, modes and a copy of every register."""
        moving = self.run is not None or self.qd.any() or self.qdd.any() or self.error.any()
        if moving or self._kinematic_fields is None:
            self._kinematic_fields, self._currents_now = self._kinematics_report()
        noise = self._sensor_noise()
        actual_current = self._currents_now + noise[:6]
        force = noise[6:]
        program_running = self.runtime_state == RUNTIME_PLAYING
        status = 1 | (2 if program_running else 0) if self.robot_mode == ROBOT_MODE_RUNNING else 0
        fields = {
            **self._kinematic_fields,
            "timestamp": self.cycle * self.period,
            "actual_current": actual_current.tolist(), "joint_control_output": actual_current.tolist(),
            "actual_TCP_force": force.tolist(), "tcp_force_scalar": math.hypot(*force[:3].tolist()),
            "actual_robot_current": 0.6 + 0.1 * float(np.abs(actual_current).sum()),
            "robot_mode": self.robot_mode,
            "safety_mode": self.safety_mode, "safety_status": self.safety_mode,
            "safety_status_bits": self.safety_bits,
            "runtime_state": self.runtime_state,
            "robot_status_bits": status,
            "payload": self.payload_mass, "payload_cog": self.payload_cog.tolist(),
            "payload_inertia": self.payload_inertia.tolist(),
            "out_int": list(self.out_int), "out_double": list(self.out_double),
            "in_int": list(self.in_int), "in_double": list(self.in_double),
        }
        return CycleState(self.cycle, fields)

    def _sensor_noise(self) -> np.ndarray:
        """This cycle's sensor noise: 6 joint currents (A), then force (N) and torque (N·m), drawn
        in blocks of ``NOISE_BLOCK`` cycles (one generator call instead of three per cycle)."""
        if self._noise_next >= len(self._noise_block):
            self._noise_block = self._sensor_rng.normal(0.0, 1.0, (NOISE_BLOCK, 12)) * NOISE_SCALE
            self._noise_next = 0
        row = self._noise_block[self._noise_next]
        self._noise_next += 1
        return row

    def _kinematics_report(self) -> tuple[dict[str, Any], np.ndarray]:
        """The fields that follow from joints, speeds and payload, and the joint currents (no noise)."""
        q_actual = self.q + self.error
        frames = self.kin.joint_frames(q_actual)
        torque, current = self._currents(frames, self.qdd)
        fields = {
            "target_q": self.q.tolist(), "actual_q": q_actual.tolist(),
            "target_qd": self.qd.tolist(), "actual_qd": (self.qd + self.error_rate).tolist(),
            "target_qdd": self.qdd.tolist(),
            "target_current": current.tolist(), "target_moment": torque.tolist(),
            "actual_TCP_pose": matrix_to_pose6(self.actual_tcp_pose).tolist(),
            "target_TCP_pose": matrix_to_pose6(self.tcp_pose).tolist(),
            "actual_TCP_speed": self.actual_tcp_speed.tolist(), "target_TCP_speed": self.tcp_speed.tolist(),
            "joint_mode": [JOINT_RUNNING_MODE] * 6,
            "joint_temperatures": [31.0, 32.5, 32.0, 34.0, 35.0, 35.5],
            "actual_main_voltage": 48.0, "actual_robot_voltage": 48.0,
            "actual_joint_voltage": [47.8] * 6,
            "actual_tool_accelerometer": (frames[6][:3, :3].T @ -GRAVITY).tolist(),
            "speed_scaling": 1.0, "target_speed_fraction": 1.0,
            "actual_execution_time": 0.25,
            "elbow_position": frames[3][:3, 3].tolist(),
            "elbow_velocity": [0.0, 0.0, 0.0],
        }
        return fields, current

    def describe(self) -> dict[str, Any]:
        with self.lock:
            run = self.run
            return {
                "time": self.t_sim,
                "cycle": self.cycle,
                "timestamp": self.cycle * self.period,
                "q": self.q.tolist(),
                "actual_q": (self.q + self.error).tolist(),
                "tcp_pose": matrix_to_pose6(self.tcp_pose).tolist(),
                "actual_tcp_pose": matrix_to_pose6(self.actual_tcp_pose).tolist(),
                "tcp_offset": self.tcp_offset.tolist(),
                "flange_pose": matrix_to_pose6(self.tcp_pose @ invert(pose6_to_matrix(self.tcp_offset))).tolist(),
                "moving": run is not None,
                "phase": "idle" if run is None else run.phase,
                "runtime_state": self.runtime_state,
                "robot_mode": self.robot_mode,
                "safety_mode": self.safety_mode,
                "safety_status_bits": self.safety_bits,
                "program": getattr(self.program, "name", None),
                "payload": self.payload_mass,
                "payload_cog": self.payload_cog.tolist(),
                "late_cycles": self.late_cycles,
                "skipped_cycles": self.skipped_cycles,
                "stalls": self.stalls,
            }


def _twist(before: np.ndarray, after: np.ndarray, h: float) -> np.ndarray:
    """Linear and angular velocity that takes pose ``before`` to ``after`` in ``h`` seconds."""
    linear = (after[:3, 3] - before[:3, 3]) / h
    angular = matrix_to_rotvec(after[:3, :3] @ before[:3, :3].T) / h
    return np.concatenate([linear, angular])
