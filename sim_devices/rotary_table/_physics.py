"""Physics of a precision rotary table (the angle reference of the angle calibration).

Angles
------
- ``motor``: the angle of the encoder disk (on the drive side of the gear). The servo moves it on an
  inertia-limited trapezoidal profile (``max_speed``, ``acceleration = peak_torque / inertia``).
- ``true`` table angle = ``motor − d·backlash/2``, ``d`` the sign of the last motion (the play is taken
  up in the direction of travel). This is what goes into the ``World``.
- encoder reading = ``motor + E(motor) − zero``, ``E`` a once-per-revolution sinusoid (the periodic
  error of a real ring encoder), plus a little clipped Gaussian noise, quantised to counts. ``zero``
  is the power-on position until the table is homed; then the reference mark defines ``true = 0``.

The servo closes its loop on the reading: it plans the motor motion so that the noise-free reading
lands on the commanded count, so *commanded ≈ reported ≠ true*, and ``|reported − true|`` stays
below ``TableConfig.reported_error_bound()`` once homed (periodic error, backlash, quantisation, 3σ).

Power-on state and limits
-------------------------
The controller powers on with the servo off and the axis unreferenced; it refuses moves until the
servo is on and (with ``requires_homing``, the default, as on a PI controller) the reference move
has been made. One set of soft limits (``travel_min``/``travel_max``, on the reported angle) is
checked here, before any motion starts, so every protocol face refuses the same targets.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from sim_devices._config import checked_fields
from sim_devices._transforms import ARCSEC


class CommandRefused(Exception):
    """The drive cannot execute a command now.

    ``reason`` says why, for the protocol faces to answer with their own codes: ``"alarm"``,
    ``"servo_off"``, ``"unreferenced"``, or (``ValueRefused``) ``"value"`` and ``"travel"``.
    """

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason


class ValueRefused(CommandRefused):
    """A value the drive never accepts (a speed outside its range, a target beyond the soft limits)."""

    def __init__(self, message: str, reason: str = "value") -> None:
        super().__init__(message, reason)


@dataclass(frozen=True)
class TableConfig:
    """Physical parameters of the twin table. SI units (rad, s, kg·m², N·m)."""

    max_speed: float = 0.5  # rad/s (≈ 29 °/s)
    inertia: float = 0.05  # kg·m², table + load
    peak_torque: float = 0.1  # N·m  →  acceleration 2 rad/s²
    counts_per_rev: int = 16_777_216  # encoder resolution, 2**24 (0.077″)
    periodic_error: float = 0.30 * ARCSEC  # amplitude of the once-per-rev encoder error
    periodic_phase: float = 0.0  # rad, phase of that error at the reference mark (0: it vanishes there)
    backlash: float = 0.10 * ARCSEC
    noise_std: float = 0.01 * ARCSEC  # reading noise, clipped at 3σ
    settle_time: float = 0.02  # s after the profile ends until "in position"
    home_speed: float = 0.25  # rad/s
    home_overshoot: float = math.radians(0.5)  # homing approaches the mark from below
    requires_homing: bool = True  # refuse moves before the reference move (a PI controller's default)
    travel_min: float = -200.0 * math.pi  # rad, soft limits of the reported angle: ±100 turns (±36000°),
    travel_max: float = 200.0 * math.pi  # as far as a cabled fixture on the table may wind
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.travel_min < self.travel_max:
            raise ValueError(f"table config: travel_min ({self.travel_min!r}) must be below travel_max "
                             f"({self.travel_max!r})")

    @property
    def acceleration(self) -> float:
        return self.peak_torque / self.inertia

    def reported_error_bound(self) -> float:
        """Largest ``|reported − true|`` the model can produce once homed (rad).

        The counter is zeroed at the reference mark approached from below, so the periodic error is
        counted from its value at the mark, and an approach from above adds the whole backlash.
        """
        quantum = 2.0 * math.pi / self.counts_per_rev
        periodic = self.periodic_error * (1.0 + abs(math.sin(self.periodic_phase)))
        return periodic + self.backlash + quantum / 2.0 + 3.0 * self.noise_std

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | TableConfig | None) -> TableConfig:
        if isinstance(data, TableConfig):
            return data
        return cls(**checked_fields(cls, data, "table config"))

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class _Segment:
    t0: float
    duration: float
    p0: float
    v0: float
    a: float

    def at(self, t: float) -> tuple[float, float]:
        dt = min(max(t - self.t0, 0.0), self.duration)
        return self.p0 + self.v0 * dt + 0.5 * self.a * dt * dt, self.v0 + self.a * dt

    @property
    def end(self) -> float:
        return self.t0 + self.duration


def _trapezoid(t0: float, p0: float, p1: float, vmax: float, amax: float) -> list[_Segment]:
    """Rest-to-rest time-optimal profile from ``p0`` to ``p1``."""
    distance = p1 - p0
    sign = 1.0 if distance >= 0 else -1.0
    d = abs(distance)
    if d == 0.0:
        return []
    t_acc = vmax / amax
    if amax * t_acc * t_acc >= d:  # triangle: never reaches vmax
        t_acc = math.sqrt(d / amax)
        vpeak, t_cruise = amax * t_acc, 0.0
    else:
        vpeak, t_cruise = vmax, (d - amax * t_acc * t_acc) / vmax
    segments = [_Segment(t0, t_acc, p0, 0.0, sign * amax)]
    p, _ = segments[-1].at(segments[-1].end)
    if t_cruise > 0:
        segments.append(_Segment(segments[-1].end, t_cruise, p, sign * vpeak, 0.0))
        p, _ = segments[-1].at(segments[-1].end)
    segments.append(_Segment(segments[-1].end, t_acc, p, sign * vpeak, -sign * amax))
    return segments


class TablePhysics:
    """The table's state over time. Thread-safe; time from ``clock``.

    Parameters
    ----------
    config : TableConfig
    clock : callable
        Seconds (monotonic); inject a fake clock in tests.
    on_change : callable, optional
        ``on_change(true_angle, settled)`` whenever the truth may have changed (see ``update``). It is
        called under the table's lock, so it must not block (the host hands the state to a thread).
    initial_angle : float
        True angle at power-on (rad).
    seen : callable, optional
        ``seen()`` is true once everything ``on_change`` was told has reached the world (every camera
        has it): the drive reports in position only then, as a real table's stage is in position only
        once it is, so frames taken after "in position" never show an older angle.
    """

    def __init__(self, config: TableConfig | None = None, clock: Callable[[], float] = time.monotonic,
                 on_change: Callable[[float, bool], None] | None = None, initial_angle: float = 0.0,
                 seen: Callable[[], bool] | None = None) -> None:
        self.config = config or TableConfig()
        self.clock = clock
        self.on_change = on_change
        self.seen = seen
        self._lock = threading.RLock()
        seed_seq = np.random.SeedSequence([self.config.seed, 0x7AB1E])
        self._rng = np.random.default_rng(seed_seq)
        self._mark = self.config.backlash / 2.0  # motor angle of the reference mark (true 0, approached from below)
        self._phase = self.config.periodic_phase
        self._direction = 1.0
        self._motor0 = initial_angle + self._direction * self.config.backlash / 2.0
        self._segments: list[_Segment] = []
        self._profile_end = self.clock() - self.config.settle_time
        self._speed = self.config.max_speed
        self._acceleration = self.config.acceleration
        self._zero = self._motor0 + self._periodic(self._motor0)  # reading 0 at power-on
        self._target_counts = 0
        self._homed = False
        self._homing = False
        self._enabled = False  # power-on: servo off, unreferenced
        self._alarms: set[str] = set()
        self._stopping = False
        self._last_published: tuple[float, bool] | None = None

    # ----------------------------------------------------------------------------- model
    def _periodic(self, motor: float) -> float:
        return self.config.periodic_error * math.sin(motor - self._mark + self._phase)

    @property
    def quantum(self) -> float:
        return 2.0 * math.pi / self.config.counts_per_rev

    def _motor_at(self, t: float) -> tuple[float, float]:
        for segment in self._segments:
            if t < segment.end:
                return segment.at(t)
        if self._segments:
            return self._segments[-1].at(self._segments[-1].end)[0], 0.0
        return self._motor0, 0.0

    def _motor_for_reading(self, reading: float) -> float:
        """Motor angle whose noise-free reading is ``reading`` (fixed point; |E'| ≪ 1)."""
        motor = reading + self._zero
        for _ in range(4):
            motor = reading + self._zero - self._periodic(motor)
        return motor

    def _finish_if_done(self, t: float) -> None:
        if self._segments and t >= self._segments[-1].end:
            self._direction = self._direction_at(t)
            self._motor0 = self._segments[-1].at(self._segments[-1].end)[0]
            self._segments = []
            self._stopping = False
            if self._homing:  # at the reference mark: the true angle is zero here, so is the counter
                self._homing = False
                self._homed = True
                self._zero = self._motor0 + self._periodic(self._motor0)
                self._target_counts = 0

    def _direction_at(self, t: float) -> float:
        """Sign of the last motion started before ``t`` (the side the backlash is taken up on)."""
        direction = self._direction
        for segment in self._segments:
            if segment.t0 <= t:
                moving = segment.v0 if segment.v0 != 0.0 else segment.a
                if moving != 0.0:
                    direction = math.copysign(1.0, moving)
        return direction

    def _plan(self, t: float, motor_target: float, *, via: float | None = None, speed: float | None = None) -> None:
        motor, velocity = self._motor_at(t)
        self._direction = self._direction_at(t)
        segments: list[_Segment] = []
        start_time, start = t, motor
        if velocity != 0.0:  # decelerate to rest first, then go
            t_dec = abs(velocity) / self._acceleration
            segments.append(_Segment(t, t_dec, motor, velocity, -math.copysign(self._acceleration, velocity)))
            start_time, start = segments[-1].end, segments[-1].at(segments[-1].end)[0]
        vmax = speed or self._speed
        for goal in ([via] if via is not None else []) + [motor_target]:
            legs = _trapezoid(start_time, start, goal, vmax, self._acceleration)
            segments.extend(legs)
            if legs:
                start_time, start = legs[-1].end, goal
        self._motor0 = motor
        self._segments = segments
        self._profile_end = segments[-1].end if segments else t

    # ----------------------------------------------------------------------------- commands
    def _check_can_move(self, needs_home: bool) -> None:
        if self._alarms:
            raise CommandRefused(f"alarm present ({', '.join(sorted(self._alarms))})", "alarm")
        if not self._enabled:
            raise CommandRefused("servo off (motor disabled)", "servo_off")
        if needs_home and self.config.requires_homing and not self._homed:
            raise CommandRefused("not referenced (home first)", "unreferenced")

    def check_travel(self, counts: int) -> None:
        """Raise ``ValueRefused`` (reason ``"travel"``) if ``counts`` lies beyond the soft limits."""
        angle = int(counts) * self.quantum
        low, high = self.config.travel_min, self.config.travel_max
        if not low <= angle <= high:
            raise ValueRefused(f"target {math.degrees(angle):.6g}° outside the soft limits "
                               f"[{math.degrees(low):.6g}°, {math.degrees(high):.6g}°]", "travel")

    def move_to_counts(self, counts: int, speed: float | None = None) -> None:
        """Start a move to the reported angle ``counts``; ``CommandRefused`` (nothing moves) if the
        drive cannot move now or the target is beyond the soft limits."""
        with self._lock:
            t = self.clock()
            self._finish_if_done(t)
            self.check_travel(counts)
            self._check_can_move(True)
            self._homing = False
            self._target_counts = int(counts)
            self._plan(t, self._motor_for_reading(int(counts) * self.quantum), speed=speed)
            self._publish(t)

    def move_by_counts(self, delta: int, speed: float | None = None) -> None:
        with self._lock:
            self.move_to_counts(self._target_counts + int(delta), speed)

    def home(self) -> None:
        """Seek the reference mark (true angle 0), approaching it in the positive direction."""
        with self._lock:
            t = self.clock()
            self._finish_if_done(t)
            self._check_can_move(False)
            mark = self._mark
            motor, _ = self._motor_at(t)
            via = mark - self.config.home_overshoot if motor >= mark - self.config.home_overshoot / 2 else None
            self._homing = True
            self._homed = False
            self._plan(t, mark, via=via, speed=self.config.home_speed)
            self._publish(t)

    def stop(self) -> None:
        with self._lock:
            t = self.clock()
            self._finish_if_done(t)
            motor, velocity = self._motor_at(t)
            self._direction = self._direction_at(t)
            self._homing = False
            if velocity == 0.0:
                self._segments, self._motor0 = [], motor
            else:
                t_dec = abs(velocity) / self._acceleration
                self._segments = [_Segment(t, t_dec, motor, velocity, -math.copysign(self._acceleration, velocity))]
                self._stopping = True
                self._profile_end = self._segments[-1].end
            # After a stop the position command is wherever the table comes to rest.
            rest = self._segments[-1].at(self._segments[-1].end)[0] if self._segments else motor
            self._target_counts = int(round((rest + self._periodic(rest) - self._zero) / self.quantum))
            self._publish(t)

    def set_speed(self, speed: float) -> None:
        if not (0.0 < speed <= self.config.max_speed * (1 + 1e-9)):
            raise ValueRefused(f"speed {speed:.6g} rad/s outside (0, {self.config.max_speed:.6g}]")
        with self._lock:
            self._speed = min(float(speed), self.config.max_speed)

    def set_acceleration(self, acceleration: float) -> None:
        if not (0.0 < acceleration <= self.config.acceleration * (1 + 1e-9)):
            raise ValueRefused(f"acceleration {acceleration:.6g} rad/s² outside (0, {self.config.acceleration:.6g}]")
        with self._lock:
            self._acceleration = min(float(acceleration), self.config.acceleration)

    def enable(self, on: bool = True) -> None:
        with self._lock:
            if not on:
                self.stop()
            self._enabled = bool(on)

    def raise_alarm(self, name: str) -> None:
        """A drive alarm (``following_error``, ``encoder_fault`` ...): the table stops and refuses moves."""
        with self._lock:
            self.stop()
            self._alarms.add(name)

    def alarm_reset(self) -> None:
        with self._lock:
            self._alarms.clear()

    # ----------------------------------------------------------------------------- readers
    @property
    def speed(self) -> float:
        return self._speed

    @property
    def acceleration(self) -> float:
        return self._acceleration

    def read_counts(self) -> int:
        """The encoder counter now (noisy, quantised)."""
        with self._lock:
            t = self.clock()
            self.update(t)
            motor, _ = self._motor_at(t)
            noise = float(np.clip(self._rng.normal(0.0, self.config.noise_std), -3 * self.config.noise_std,
                                  3 * self.config.noise_std)) if self.config.noise_std > 0 else 0.0
            reading = motor + self._periodic(motor) - self._zero + noise
            return int(round(reading / self.quantum))

    def true_angle(self, t: float | None = None) -> float:
        with self._lock:
            t = self.clock() if t is None else t
            motor, _ = self._motor_at(t)
            return motor - self._direction_at(t) * self.config.backlash / 2.0

    def status(self) -> dict[str, Any]:
        with self._lock:
            t = self.clock()
            self.update(t)
            _, velocity = self._motor_at(t)
            moving = bool(self._segments) and t < self._profile_end
            return {
                "enabled": self._enabled,
                "moving": moving,
                "stopping": self._stopping and moving,
                "homing": self._homing,
                "homed": self._homed,
                "in_position": (not moving and not self._alarms and t >= self._profile_end + self.config.settle_time
                                and (self.seen is None or self.seen())),
                "alarms": sorted(self._alarms),
                "velocity": velocity,
                "target_counts": self._target_counts,
            }

    def settled(self, t: float | None = None) -> bool:
        with self._lock:
            t = self.clock() if t is None else t
            return not self._segments and t >= self._profile_end + self.config.settle_time

    # ----------------------------------------------------------------------------- truth out
    def update(self, t: float | None = None) -> None:
        """Advance to ``t`` and tell ``on_change`` the truth (called on every access and by a ticker)."""
        with self._lock:
            t = self.clock() if t is None else t
            self._finish_if_done(t)
            self._publish(t)

    def _publish(self, t: float) -> None:
        if self.on_change is None:
            return
        state = (self.true_angle(t), self.settled(t))
        if state != self._last_published:
            self._last_published = state
            self.on_change(*state)

    def forget_published(self) -> None:
        """Make the next ``update`` publish again (e.g. the OPR was just put on the table)."""
        with self._lock:
            self._last_published = None
