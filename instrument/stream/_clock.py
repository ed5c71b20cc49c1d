"""Putting camera timestamps on the robot controller's clock (docs/dynamic.md, "Clocks").

Two estimates, for two situations:

- :func:`estimate_clock_offset` — **paired timestamps**: the same events (trigger pulses) stamped
  by both clocks, e.g. the controller's time of the digital output that fires the cameras' trigger
  line, and each camera's frame timestamp. A straight line t_robot = a + r·(t_camera − c) through
  the pairs gives the offset and the rate (the drift of one crystal against the other, typically
  tens of ppm); a robust refit drops pairs that were mis-paired or delayed (more than
  ``OUTLIER_SIGMAS`` robust σ off). A constant latency between an event and its stamp on either
  side cannot be seen in the timestamps: it goes into the offset, and must be known separately
  (e.g. a camera's stamp at exposure start is half an exposure before the image's mean time).
- :func:`estimate_time_lag` — **motion**: with no paired events, the lag between the instrument's
  pose stream and the robot's own position log (``actual_TCP_pose`` at 500 Hz) is found by sliding
  one speed profile over the other. Speed is used rather than position because it does not depend
  on the frames the two are expressed in; the lag is where the mean squared speed difference is
  least, refined by a parabola through the three best shifts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

OUTLIER_SIGMAS = 4.0


class ClockError(ValueError):
    """Unusable input for a clock estimate; the message names the argument and the fault."""


@dataclass(frozen=True)
class ClockModel:
    """t_robot = robot_reference + rate·(t_camera − camera_reference), seconds.

    Attributes
    ----------
    camera_reference, robot_reference : float
        s, a pair of corresponding instants (the mean of the fitted pairs: the offset is best
        known there).
    rate : float
        Robot seconds per camera second (1 + drift).
    residual_rms, max_residual : float
        s, of the pairs kept in the fit (the timestamp jitter).
    pairs, rejected : int
        Pairs used, and pairs left out as outliers.
    offset_std, rate_std : float
        Standard errors of ``robot_reference`` (at ``camera_reference``) and of ``rate``.
    """

    camera_reference: float = 0.0
    robot_reference: float = 0.0
    rate: float = 1.0
    residual_rms: float = 0.0
    max_residual: float = 0.0
    pairs: int = 0
    rejected: int = 0
    offset_std: float = 0.0
    rate_std: float = 0.0

    @classmethod
    def identity(cls) -> ClockModel:
        """The camera already stamps on the robot's clock."""
        return cls()

    @classmethod
    def from_offset(cls, offset: float) -> ClockModel:
        """t_robot = t_camera + offset (a known, constant offset)."""
        return cls(0.0, float(offset))

    @property
    def drift(self) -> float:
        """rate − 1 (e.g. 2e-5 = 20 ppm)."""
        return self.rate - 1.0

    def to_robot(self, t_camera):
        """Camera time(s) → robot time(s), s (scalar in, float out; array in, array out)."""
        if isinstance(t_camera, float):  # one timestamp per frame in a stream: plain float arithmetic
            return float(self.robot_reference + self.rate * (t_camera - self.camera_reference))
        value = self.robot_reference + self.rate * (np.asarray(t_camera, dtype=float) - self.camera_reference)
        return float(value) if value.ndim == 0 else value


def _paired(camera_times, robot_times) -> tuple[np.ndarray, np.ndarray]:
    try:
        camera = np.asarray(camera_times, dtype=float).reshape(-1)
        robot = np.asarray(robot_times, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ClockError("camera_times, robot_times: expected two 1-D arrays of times (s)") from None
    if camera.shape != robot.shape:
        raise ClockError(f"camera_times and robot_times must pair up one to one, got {camera.size} and {robot.size}")
    keep = np.isfinite(camera) & np.isfinite(robot)  # NaN marks an event one side missed
    return camera[keep], robot[keep]


def _line(camera: np.ndarray, robot: np.ndarray, fit_rate: bool) -> tuple[float, float, float, np.ndarray]:
    c0, r0 = float(camera.mean()), float(robot.mean())
    dc = camera - c0
    rate = float((dc @ (robot - r0)) / (dc @ dc)) if fit_rate else 1.0
    return c0, r0, rate, robot - (r0 + rate * dc)


def estimate_clock_offset(camera_times, robot_times, *, fit_rate: bool = True) -> ClockModel:
    """Clock model from paired timestamps of the same events (see the module docstring).

    Parameters
    ----------
    camera_times, robot_times : (n,) arrays
        s; entry k of both is the same event. NaN on either side: the pair is skipped.
    fit_rate : bool
        Fit the rate (drift) too; False fixes it at 1 (short records, or clocks known to agree).

    Returns
    -------
    ClockModel

    Raises
    ------
    ClockError
        Mismatched arrays, fewer than 3 usable pairs (2 with ``fit_rate=False``), or camera times
        that do not spread (the rate cannot be fitted).
    """
    camera, robot = _paired(camera_times, robot_times)
    needed = 3 if fit_rate else 2
    if camera.size < needed:
        raise ClockError(f"need at least {needed} paired timestamps, got {camera.size}")
    if fit_rate and np.ptp(camera) <= 0.0:
        raise ClockError("camera_times: all equal; the rate cannot be fitted (use fit_rate=False)")
    c0, r0, rate, residual = _line(camera, robot, fit_rate)
    scale = 1.4826 * float(np.median(np.abs(residual - np.median(residual))))
    limit = OUTLIER_SIGMAS * scale if scale > 0 else np.inf
    keep = np.abs(residual - np.median(residual)) <= limit
    if np.count_nonzero(keep) >= needed and not keep.all():
        c0, r0, rate, residual = _line(camera[keep], robot[keep], fit_rate)
    else:
        keep = np.ones(camera.size, bool)
    n = int(np.count_nonzero(keep))
    dof = max(n - (2 if fit_rate else 1), 1)
    sigma = float(np.sqrt(residual @ residual / dof))
    spread = camera[keep] - c0
    rate_std = sigma / float(np.sqrt(spread @ spread)) if fit_rate else 0.0
    return ClockModel(
        camera_reference=c0,
        robot_reference=r0,
        rate=rate,
        residual_rms=float(np.sqrt(np.mean(residual**2))),
        max_residual=float(np.abs(residual).max()),
        pairs=n,
        rejected=int(camera.size - n),
        offset_std=sigma / np.sqrt(n),
        rate_std=rate_std,
    )


@dataclass(frozen=True)
class TimeLag:
    """Lag of a measured motion behind a reference one: t_reference = t_measured + lag.

    Attributes
    ----------
    lag : float
        s.
    rms_speed_difference : float
        m/s, at the best lag (how well the two speed profiles agree).
    samples : int
        Measured samples in the overlap at the best lag.
    """

    lag: float
    rms_speed_difference: float
    samples: int


def _speed(t: np.ndarray, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return t[1:-1], np.linalg.norm(positions[2:] - positions[:-2], axis=1) / (t[2:] - t[:-2])


def estimate_time_lag(t_measured, positions_measured, t_reference, positions_reference, *, max_lag: float) -> TimeLag:
    """Lag between two recordings of one motion from their speed profiles (see the module docstring).

    Parameters
    ----------
    t_measured, positions_measured : (N,), (N, 3) arrays
        The instrument's stream (s on its clock, m in any frame).
    t_reference, positions_reference : (M,), (M, 3) arrays
        The robot's log (s on the robot clock, m in any frame).
    max_lag : float
        s, the largest |lag| searched.

    Returns
    -------
    TimeLag
        ``lag`` such that t_reference = t_measured + lag; add it to the measured times.
    """
    arrays = []
    for name, t, p in (("measured", t_measured, positions_measured), ("reference", t_reference, positions_reference)):
        times, points = np.asarray(t, dtype=float), np.asarray(p, dtype=float)
        if times.ndim != 1 or points.shape != (len(times), 3) or len(times) < 5:
            raise ClockError(f"{name}: expected (N,) times and (N, 3) positions with N ≥ 5")
        if np.any(np.diff(times) <= 0) or not np.all(np.isfinite(points)):
            raise ClockError(f"{name}: times must increase strictly and positions be finite")
        arrays.append(_speed(times, points))
    (tm, vm), (tr, vr) = arrays
    if not max_lag > 0:
        raise ClockError(f"max_lag: must be positive, got {max_lag!r}")
    step = 0.5 * min(float(np.median(np.diff(tm))), float(np.median(np.diff(tr))))
    lags = np.arange(-max_lag, max_lag + step / 2, step)

    def mismatch(lag: float) -> tuple[float, int]:
        shifted = tm + lag
        inside = (shifted >= tr[0]) & (shifted <= tr[-1])
        if np.count_nonzero(inside) < 3:
            return np.inf, 0
        difference = vm[inside] - np.interp(shifted[inside], tr, vr)
        return float(np.mean(difference**2)), int(np.count_nonzero(inside))

    costs = np.array([mismatch(lag)[0] for lag in lags])
    if not np.any(np.isfinite(costs)):
        raise ClockError("the two recordings do not overlap within ±max_lag")
    k = int(np.argmin(costs))
    best = float(lags[k])
    if 0 < k < len(lags) - 1 and np.all(np.isfinite(costs[k - 1 : k + 2])):
        c_minus, c0, c_plus = costs[k - 1 : k + 2]
        curvature = c_minus - 2 * c0 + c_plus
        if curvature > 0:
            best += 0.5 * step * (c_minus - c_plus) / curvature
    cost, samples = mismatch(best)
    return TimeLag(best, float(np.sqrt(cost)), samples)
