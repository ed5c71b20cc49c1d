"""The joint servos of the UR twin: following error during motion, a damped residual after it.

Each joint's error ``e = q_actual − q_target`` obeys a second-order law driven by the target's
motion::

    ë + 2 ζ ω ė + ω² e = −ω² τ q̇_target − q̈_target

At constant speed the error settles at ``e = −τ q̇`` (the actual joint lags the target by ``τ``
seconds, so the lag grows with speed); every change of acceleration (the ends of the ramps, the
end of the profile) leaves a damped oscillation at ``ω·sqrt(1 − ζ²)`` that decays as
``exp(−ζ ω t)``: the settling a real arm shows after a move. Each joint's ``ω`` is the configured
frequency times a seeded factor, so the joints ring slightly differently, reproducibly.

``step`` integrates exactly over a step of any length (the forcing is held constant over the
step), so the law is stable at any time scale.
"""

from __future__ import annotations

import numpy as np


class JointServos:
    """Error dynamics of six joint servos (see module docstring).

    Parameters
    ----------
    frequency : float
        Natural frequency ω / 2π, Hz (before the per-joint factor).
    damping : float
        Damping ratio ζ, 0 < ζ < 1 (underdamped: the residual oscillates).
    lag : float
        τ, seconds: the following error at constant speed is ``τ · speed``.
    spread : float
        Relative standard deviation of the per-joint frequency factor (seeded by ``rng``).
    rng : numpy Generator
        Draws the per-joint factors.
    """

    def __init__(self, frequency: float, damping: float, lag: float, spread: float, rng: np.random.Generator) -> None:
        if frequency <= 0 or not 0.0 < damping < 1.0 or lag < 0:
            raise ValueError(f"servo: need frequency > 0, 0 < damping < 1 and lag ≥ 0; got {frequency}, {damping}, "
                             f"{lag}")
        factors = np.clip(1.0 + spread * rng.standard_normal(6), 0.5, 1.5)
        self.omega = 2.0 * np.pi * frequency * factors
        self.zeta = float(damping)
        self.lag = float(lag)
        self.sigma = self.zeta * self.omega  # decay rate, 1/s
        self.omega_d = self.omega * np.sqrt(1.0 - self.zeta**2)

    def step(self, error: np.ndarray, rate: np.ndarray, target_velocity: np.ndarray,
             target_acceleration: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
        """Error and its rate after ``h`` seconds, with the target's velocity and acceleration held."""
        if h <= 0:
            return error, rate
        forcing = -(self.omega**2) * self.lag * target_velocity - target_acceleration
        steady = forcing / self.omega**2
        x0, v0 = error - steady, rate
        decay = np.exp(-self.sigma * h)
        cos, sin = np.cos(self.omega_d * h), np.sin(self.omega_d * h)
        x1 = decay * (x0 * (cos + self.sigma / self.omega_d * sin) + v0 * sin / self.omega_d)
        v1 = decay * (-x0 * self.omega**2 / self.omega_d * sin + v0 * (cos - self.sigma / self.omega_d * sin))
        return x1 + steady, v1

    def settled(self, error: np.ndarray, rate: np.ndarray, tolerance: float) -> bool:
        """Whether the residual's envelope is below ``tolerance`` (rad) on every joint."""
        # Energy-like amplitude of a damped oscillator: |e|² + (ė/ω)² bounds the next peaks.
        amplitude = np.sqrt(error**2 + (rate / self.omega) ** 2)
        return bool(np.all(amplitude < tolerance))

    def settling_time(self, amplitude: float, tolerance: float) -> float:
        """Seconds for an envelope ``amplitude`` (rad) to decay below ``tolerance`` on the slowest joint."""
        if amplitude <= tolerance:
            return 0.0
        return float(np.log(amplitude / tolerance) / np.min(self.sigma))
