"""ISO 9283 characteristics of a pose being reached: position stabilisation time and position
overshoot (ISO 9283:1998 clauses 7.4 and 7.5), positioning time and minimum positioning time
(clause 9). Definitions, and how far they could be checked against the standard: docs/dynamic.md.

Input is a time series of measured positions while the robot arrives (t in s, positions in m, one
row per sample, times strictly increasing) and the instant of the robot's "attained pose" signal.
Times of crossing the band are interpolated linearly between samples; the overshoot peak is refined
by a parabola through the three samples around the sampled maximum.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from instrument.iso9283._errors import ISO9283Error

SETTLE_FRACTION = 0.2  # default attained position: mean over this share of the samples after the signal
HOLD_FRACTION = 0.1  # default hold: this share of the record after the signal (or after the departure)


@dataclass(frozen=True)
class PoseStabilisation:
    """Position stabilisation time and overshoot of one arrival at a pose (ISO 9283 7.4, 7.5).

    Attributes
    ----------
    stabilisation_time : float
        s from ``t_signal`` until the distance to the attained position stays within ``band``;
        0 if it is within the band from the signal on; NaN if it never stays within it before the
        record ends.
    overshoot : float
        m, the largest excursion beyond the attained position along the approach direction after
        the start of the overshoot window (the signal, or the first entry into the band); 0 if none.
    attained : (3,) array
        The attained position, m (given, or the mean of the record's last samples).
    approach : (3,) array
        Unit approach direction used for the overshoot.
    band : float
        m, the stabilisation band (radius about the attained position).
    t_signal : float
        s, the robot's attained-pose signal.
    settled_time : float
        s, the absolute time at which the position stays within the band (NaN if never).
    band_entry_time : float
        s, the first time at or after the record's start that the position enters the band (NaN if never).
    overshoot_time : float
        s, when the overshoot peak occurs (NaN when the overshoot is 0).
    distance : (N,) array
        m, distance of every sample from the attained position (for plots).
    """

    stabilisation_time: float
    overshoot: float
    attained: np.ndarray
    approach: np.ndarray
    band: float
    t_signal: float
    settled_time: float
    band_entry_time: float
    overshoot_time: float
    distance: np.ndarray


@dataclass(frozen=True)
class PositioningTime:
    """Time from leaving the start position to being stabilised at the next one (ISO 9283 9).

    Attributes
    ----------
    positioning_time : float
        s, ``settled_time − departure_time`` (NaN if the record never settles).
    departure_time : float
        s, when the distance from the start position first exceeds the band.
    settled_time : float
        s, from then on the distance to the attained position stays within the band.
    distance : float
        m, between the start and the attained position.
    """

    positioning_time: float
    departure_time: float
    settled_time: float
    distance: float


@dataclass(frozen=True)
class MinimumPositioningTime:
    """The least mean positioning time over the tried speed/acceleration settings (ISO 9283 9).

    Attributes
    ----------
    minimum : float
        s, the smallest of ``per_setting`` (NaN settings are skipped; NaN if all are).
    setting : str or None
        The setting that reached it.
    per_setting : dict str → float
        s, the mean positioning time of each setting's cycles (NaN if any cycle never settled).
    cycles : dict str → list of PositioningTime
    """

    minimum: float
    setting: str | None
    per_setting: dict[str, float]
    cycles: dict[str, list[PositioningTime]]


def _series(t, positions) -> tuple[np.ndarray, np.ndarray]:
    try:
        times = np.asarray(t, dtype=float)
        points = np.asarray(positions, dtype=float)
    except (TypeError, ValueError):
        raise ISO9283Error("t and positions must be numeric arrays: t (N,) s, positions (N, 3) m") from None
    if times.ndim != 1 or len(times) < 3:
        raise ISO9283Error(f"t: expected a 1-D array of at least 3 sample times (s), got shape {times.shape}")
    if points.shape != (len(times), 3):
        raise ISO9283Error(
            f"positions: expected shape ({len(times)}, 3) (one x, y, z row per time, m), got {points.shape}"
        )
    if not (np.all(np.isfinite(times)) and np.all(np.isfinite(points))):
        raise ISO9283Error("t and positions must be finite (drop samples the instrument could not measure)")
    if np.any(np.diff(times) <= 0.0):
        raise ISO9283Error("t: sample times must increase strictly")
    return times, points


def _positive(value, name: str) -> float:
    number = float(value)
    if not (np.isfinite(number) and number > 0.0):
        raise ISO9283Error(f"{name}: must be a positive number, got {value!r}")
    return number


def _vector3(value, name: str) -> np.ndarray:
    array = np.asarray(value, dtype=float).reshape(-1)
    if array.shape != (3,) or not np.all(np.isfinite(array)):
        raise ISO9283Error(f"{name}: expected 3 finite numbers, got {value!r}")
    return array


def _crossing(times: np.ndarray, distance: np.ndarray, band: float, i: int) -> float:
    """Time at which the distance crosses ``band`` between samples i and i + 1 (linear)."""
    d0, d1 = distance[i], distance[i + 1]
    if d0 == d1:
        return float(times[i + 1])
    fraction = (d0 - band) / (d0 - d1)
    return float(times[i] + min(max(fraction, 0.0), 1.0) * (times[i + 1] - times[i]))


def _settled_time(
    times: np.ndarray, distance: np.ndarray, band: float, start: int, hold: float | None, origin: float
) -> float:
    """First time from which every sample at index ≥ ``start`` stays within the band (NaN if never).

    Interpolated between the last sample outside the band and the next one; ``origin`` (the
    signal, or the departure) if no sample from ``start`` on is outside. The record must then stay
    inside for ``hold`` seconds (default ``HOLD_FRACTION`` of the record from ``start``): a record
    that ends soon after its last excursion — between two swings of an oscillation that goes on —
    has not shown that it settled.
    """
    if hold is None:
        hold = HOLD_FRACTION * float(times[-1] - times[start])
    outside = np.flatnonzero(distance[start:] > band)
    if len(outside) == 0:
        return origin
    last = start + int(outside[-1])
    if last == len(times) - 1:
        return float("nan")
    settled = _crossing(times, distance, band, last)
    return settled if times[-1] - settled >= hold else float("nan")


def _refined_peak(times: np.ndarray, values: np.ndarray, k: int) -> tuple[float, float]:
    """(time, value) of the maximum near sample k: a parabola through samples k−1, k, k+1."""
    if k == 0 or k == len(values) - 1:
        return float(times[k]), float(values[k])
    (t0, t1, t2), (y0, y1, y2) = times[k - 1 : k + 2], values[k - 1 : k + 2]
    # parabola through three points (uneven spacing allowed), vertex by Lagrange form
    denominator = (t0 - t1) * (t0 - t2) * (t1 - t2)
    a = (t2 * (y1 - y0) + t1 * (y0 - y2) + t0 * (y2 - y1)) / denominator
    b = (t2 * t2 * (y0 - y1) + t1 * t1 * (y2 - y0) + t0 * t0 * (y1 - y2)) / denominator
    if not a < 0.0:
        return float(t1), float(y1)
    vertex = -b / (2.0 * a)
    if not t0 <= vertex <= t2:
        return float(t1), float(y1)
    c = y1 - a * t1 * t1 - b * t1
    return float(vertex), float(a * vertex * vertex + b * vertex + c)


def pose_stabilisation(
    t,
    positions,
    t_signal: float,
    band: float,
    *,
    attained=None,
    approach=None,
    overshoot_from: str = "signal",
    hold: float | None = None,
) -> PoseStabilisation:
    """Position stabilisation time and position overshoot of one arrival (ISO 9283 7.4, 7.5).

    Parameters
    ----------
    t : (N,) array
        Sample times, s, strictly increasing (the record should start during the approach and end
        well after the robot has settled).
    positions : (N, 3) array
        Measured positions of the measuring point, m.
    t_signal : float
        s, the instant the robot gives its "attained pose" signal, on the same clock as ``t``.
    band : float
        m, the stabilisation band: the limit the manufacturer specifies, a radius about the
        attained position.
    attained : (3,) array, optional
        The attained position; by default the mean of the last ``SETTLE_FRACTION`` of the samples
        after ``t_signal`` (at least 3).
    approach : (3,) array, optional
        Direction of the approach (need not be unit); by default from the first sample to the
        attained position.
    overshoot_from : {"signal", "band_entry"}
        Where the overshoot window starts: at ``t_signal`` (default), or at the first entry into the
        band (the standard's wording, which differs when the robot enters the band before its
        signal; see docs/dynamic.md).
    hold : float, optional
        s the record must stay within the band after the stabilisation instant for it to count;
        default ``HOLD_FRACTION`` of the record after the signal. Shorter: NaN (not shown to settle).

    Returns
    -------
    PoseStabilisation

    Raises
    ------
    ISO9283Error
        Malformed series, ``t_signal`` outside the record, a non-positive band, or an approach
        direction that cannot be set (the record starts at the attained position and none given).
    """
    times, points = _series(t, positions)
    band = _positive(band, "band")
    t_signal = float(t_signal)
    if not (times[0] <= t_signal <= times[-1]):
        raise ISO9283Error(f"t_signal: {t_signal:.6g} s lies outside the record [{times[0]:.6g}, {times[-1]:.6g}] s")
    start = int(np.searchsorted(times, t_signal, side="left"))
    if attained is None:
        after = points[start:]
        count = max(3, int(round(SETTLE_FRACTION * len(after))))
        if len(after) < count:
            raise ISO9283Error("positions: fewer than 3 samples after t_signal to find the attained position")
        target = after[-count:].mean(axis=0)
    else:
        target = _vector3(attained, "attained")
    if approach is None:
        direction = target - points[0]
        if np.linalg.norm(direction) <= band:
            raise ISO9283Error(
                "approach: the record starts within the band of the attained position; give the approach "
                "direction (e.g. the commanded move's)"
            )
    else:
        direction = _vector3(approach, "approach")
        if np.linalg.norm(direction) == 0.0:
            raise ISO9283Error("approach: must not be the zero vector")
    direction = direction / np.linalg.norm(direction)
    distance = np.linalg.norm(points - target, axis=1)
    settled = _settled_time(times, distance, band, start, hold, t_signal)
    inside = np.flatnonzero(distance <= band)
    band_entry = float("nan")
    if len(inside):
        first = int(inside[0])
        band_entry = float(times[0]) if first == 0 else _crossing(times, distance, band, first - 1)
    if overshoot_from == "signal":
        window = start
    elif overshoot_from == "band_entry":
        window = int(inside[0]) if len(inside) else len(times)
    else:
        raise ISO9283Error(f"overshoot_from: expected 'signal' or 'band_entry', got {overshoot_from!r}")
    overshoot, overshoot_time = 0.0, float("nan")
    if window < len(times):
        beyond = (points - target) @ direction
        k = window + int(np.argmax(beyond[window:]))
        if beyond[k] > 0.0:
            overshoot_time, peak = _refined_peak(times, beyond, k) if k > window else (float(times[k]), beyond[k])
            overshoot = max(float(peak), 0.0)
    return PoseStabilisation(
        stabilisation_time=settled - t_signal,
        overshoot=overshoot,
        attained=target,
        approach=direction,
        band=band,
        t_signal=t_signal,
        settled_time=settled,
        band_entry_time=band_entry,
        overshoot_time=overshoot_time,
        distance=distance,
    )


def positioning_time(
    t, positions, band: float, *, start=None, attained=None, hold: float | None = None
) -> PositioningTime:
    """Positioning time of one move (ISO 9283 9): leaving the start position → stabilised at the end.

    Parameters
    ----------
    t : (N,) array
        Sample times, s, strictly increasing; the record starts at rest at the start position and
        ends after the robot has settled at the next one.
    positions : (N, 3) array
        Measured positions, m.
    band : float
        m, the stabilisation band (as for :func:`pose_stabilisation`); also the threshold of
        "having left" the start position.
    start, attained : (3,) arrays, optional
        The start and the attained position; by default the first sample and the mean of the last
        ``SETTLE_FRACTION`` of the samples (at least 3).
    hold : float, optional
        As for :func:`pose_stabilisation` (default ``HOLD_FRACTION`` of the record after the departure).

    Returns
    -------
    PositioningTime
    """
    times, points = _series(t, positions)
    band = _positive(band, "band")
    origin = points[0] if start is None else _vector3(start, "start")
    if attained is None:
        count = max(3, int(round(SETTLE_FRACTION * len(points))))
        target = points[-count:].mean(axis=0)
    else:
        target = _vector3(attained, "attained")
    from_start = np.linalg.norm(points - origin, axis=1)
    left = np.flatnonzero(from_start > band)
    if len(left) == 0:
        raise ISO9283Error("positions: the record never leaves the band around its start position (no move)")
    first = int(left[0])
    departure = float(times[0]) if first == 0 else _crossing(times, from_start, band, first - 1)
    settled = _settled_time(times, np.linalg.norm(points - target, axis=1), band, first, hold, departure)
    return PositioningTime(settled - departure, departure, settled, float(np.linalg.norm(target - origin)))


def minimum_positioning_time(
    settings: Mapping[str, Sequence[tuple[np.ndarray, np.ndarray]]], band: float
) -> MinimumPositioningTime:
    """Minimum positioning time over the speed/acceleration settings tried (ISO 9283 9).

    Parameters
    ----------
    settings : mapping label → sequence of (t, positions) records
        The cycles (ISO 9283 asks for 3) of one move, for each setting of speed and acceleration.
    band : float
        m, the stabilisation band.

    Returns
    -------
    MinimumPositioningTime
        Each setting's mean positioning time over its cycles, and the least of them.
    """
    if not isinstance(settings, Mapping) or not settings:
        raise ISO9283Error("settings: expected a mapping label → list of (t, positions) records, got none")
    cycles: dict[str, list[PositioningTime]] = {}
    per_setting: dict[str, float] = {}
    for label, records in settings.items():
        if len(records) == 0:
            raise ISO9283Error(f"settings[{label!r}]: no records")
        cycles[str(label)] = [positioning_time(rt, rp, band) for rt, rp in records]
        per_setting[str(label)] = float(np.mean([c.positioning_time for c in cycles[str(label)]]))
    finite = {label: value for label, value in per_setting.items() if np.isfinite(value)}
    if not finite:
        return MinimumPositioningTime(float("nan"), None, per_setting, cycles)
    best = min(finite, key=lambda label: finite[label])
    return MinimumPositioningTime(finite[best], best, per_setting, cycles)
