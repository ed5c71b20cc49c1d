"""Physics of the interferometer head: what it reads for the OPR's true position in the world.

The retroreflector sits at the OPR origin. The head is aimed along one axis of M (``align``);
the true beam direction ``u`` is that axis tilted by a small random misalignment (cosine error),
and the beam line passes through where the reflector was when the head was aimed. A fringe
counter measures the optical path change along ``u`` and turns it into metres with the nominal
air's refractive index, so in real air (index n) it reads::

    reading = (1 + scale_error) * (n / n_nominal) * (u · p  -  u · p_reference) + noise

with ``p`` the OPR origin in M and ``refraction_ratio`` = n / n_nominal set by the environmental
unit (``_environment.py``) as the air drifts. The ratio applies to the whole distance from the
datum, as if the air had been the same since the datum was set (no dead-path term).
``p_reference`` is where the datum was set, or, when the count has been lost and not re-datumed,
where the beam was re-acquired (the head then flags "datum not set": the number is a count from
nowhere in particular).

Signal strength falls with the reflector's lateral offset from the beam line,
``0.95 exp(-(r / lateral_range)^2)``; below ``beam_lost_signal`` (or while a beam-break fault
blocks the beam) the beam is lost, and with it the count: the datum is gone until ``set_datum``.
Aiming the head anew (``align``) also loses the count.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from sim_devices.interferometer._config import InterferometerTwinConfig
from sim_devices.world import AXES, World, WorldState


@dataclass(frozen=True)
class HeadReading:
    displacement: float  # m, relative to the reference (meaningless unless datum_set)
    beam_ok: bool
    datum_set: bool
    signal: float  # 0..1


class InterferometerHead:
    """Thread-safe model of the head. Call ``close`` to unsubscribe from the world."""

    def __init__(self, world: World, config: InterferometerTwinConfig) -> None:
        self.world = world
        self.config = config
        constants = world.rng("interferometer")
        self.scale_error = (float(config.scale_error) if config.scale_error is not None
                            else float(constants.uniform(-config.scale_error_limit, config.scale_error_limit)))
        self._align_rng = world.rng("interferometer alignment")
        self._noise_rng = world.noise_rng("interferometer noise")
        self._normals: list[float] = []  # drawn in blocks: a numpy call per sample costs more than the sample
        self._lock = threading.Lock()
        self._signal_cache: tuple[tuple[np.ndarray, np.ndarray, np.ndarray], float] | None = None
        self._position = world.opr_in_m()[:3, 3].copy()
        world.subscribe(self._on_world)  # cache the OPR position: the feed reads it 1000 times a second
        self.datum_generation = 0
        self.refraction_ratio = 1.0  # n(air) / n(nominal), kept up to date by the environmental unit
        self._blocked_until = -np.inf  # monotonic time until which a beam-break fault blocks the beam
        self.align(config.axis)

    def close(self) -> None:
        self.world.unsubscribe(self._on_world)

    def _on_world(self, state: WorldState) -> None:
        self._position = state.opr_in_m[:3, 3].copy()

    # ------------------------------------------------------------------------------ operator actions
    def align(self, axis: str) -> dict:
        """Re-aim the head along M's ``axis`` at the reflector's current position (loses the count)."""
        if axis not in AXES:
            raise ValueError(f"interferometer: axis must be 'x', 'y' or 'z', got {axis!r}")
        index = AXES[axis]
        direction = np.zeros(3)
        direction[index] = 1.0
        tilt = self._align_rng.normal(0.0, self.config.misalignment_std, 3)
        tilt[index] = 0.0
        direction = direction + tilt
        with self._lock:
            self.axis = axis
            self.beam_direction = direction / np.linalg.norm(direction)
            self.beam_origin = self._position.copy()
            self._reference = float(self.beam_direction @ self._position)
            self.datum_set = False
            self._beam_was_ok = True
        return self.truth()

    def set_datum(self) -> bool:
        """The host's datum command: True if done, False (refused) while the beam is not OK."""
        with self._lock:
            if not self._beam_ok_locked(time.monotonic()):
                return False
            self._reference = float(self.beam_direction @ self._position)
            self.datum_set = True
            self.datum_generation = (self.datum_generation + 1) & 0xFF
            return True

    def block_beam(self, until_monotonic: float) -> None:
        with self._lock:
            self._blocked_until = max(self._blocked_until, until_monotonic)

    # ------------------------------------------------------------------------------ sampling
    def read(self, now_monotonic: float) -> HeadReading:
        """One sample at ``now_monotonic``: noise drawn, count lost if the beam is."""
        with self._lock:
            position = self._position
            beam_ok = self._beam_ok_locked(now_monotonic)
            along = float(self.beam_direction @ position)
            if not beam_ok:
                self.datum_set = False  # the fringe count is lost with the beam
            elif not self._beam_was_ok:
                self._reference = along  # counting restarts where the beam came back
            self._beam_was_ok = beam_ok
            signal = self._signal_locked() if now_monotonic >= self._blocked_until else 0.0
            noise = self._next_normal() * self.config.noise_std if self.config.noise_std else 0.0
            displacement = (1.0 + self.scale_error) * self.refraction_ratio * (along - self._reference) + noise
            return HeadReading(displacement if beam_ok else 0.0, beam_ok, self.datum_set and beam_ok, signal)

    def status(self, now_monotonic: float) -> tuple[bool, bool, float]:
        """``(beam_ok, datum_set, signal)`` without drawing a sample (for the heartbeat)."""
        with self._lock:
            beam_ok = self._beam_ok_locked(now_monotonic)
            signal = self._signal_locked() if now_monotonic >= self._blocked_until else 0.0
            return beam_ok, self.datum_set and beam_ok, signal

    def truth(self) -> dict:
        """What the head really does, for tests and the ground-truth log (JSON-friendly)."""
        with self._lock:
            along = float(self.beam_direction @ self._position)
            return {
                "axis": self.axis,
                "beam_direction": self.beam_direction.tolist(),
                "beam_origin": self.beam_origin.tolist(),
                "misalignment": float(np.arccos(np.clip(self.beam_direction[AXES[self.axis]], -1.0, 1.0))),
                "scale_error": self.scale_error,
                "refraction_ratio": self.refraction_ratio,
                "datum_set": self.datum_set,
                "datum_generation": self.datum_generation,
                "reference_along_beam": self._reference,
                "opr_position": self._position.tolist(),
                "true_displacement": along - self._reference,
                "signal": self._signal_locked(),
            }

    # ------------------------------------------------------------------------------ internals
    def _next_normal(self) -> float:
        if not self._normals:
            self._normals = self._noise_rng.standard_normal(1024).tolist()
        return self._normals.pop()

    def _signal_locked(self) -> float:
        # Read twice per sample at 1 kHz, but it changes only with the reflector's position or the
        # beam: computed again only then (the arrays are replaced, never changed in place).
        key = (self._position, self.beam_origin, self.beam_direction)
        cached = self._signal_cache
        if cached is not None and all(a is b for a, b in zip(cached[0], key)):
            return cached[1]
        offset = self._position - self.beam_origin
        lateral = offset - self.beam_direction * float(self.beam_direction @ offset)
        signal = 0.95 * float(np.exp(-(np.linalg.norm(lateral) / self.config.lateral_range) ** 2))
        self._signal_cache = (key, signal)
        return signal

    def _beam_ok_locked(self, now_monotonic: float) -> bool:
        return now_monotonic >= self._blocked_until and self._signal_locked() >= self.config.beam_lost_signal
