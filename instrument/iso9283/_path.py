"""ISO 9283 path characteristics: path accuracy AT and path repeatability RT (ISO 9283:1998
clauses 8.2, 8.3), cornering deviations CR and CO (8.5), path velocity accuracy, repeatability and
fluctuation AV, RV, FV (8.6). Definitions and how far they were checked: docs/dynamic.md.

A commanded path is reduced to m calculation points C_i with the path's unit tangent T_i there
(:class:`CommandPath`; :func:`linear_path`, :func:`circular_path`). Each attained path (one per
cycle, a time-ordered series of [x, y, z] or [x, y, z, a, b, c] rows, m and rad) is cut by the
plane through C_i normal to T_i; the cut point is interpolated linearly between the two samples on
either side of the plane (position and angles, the angles unwrapped along the path first).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from instrument.iso9283._data import wrap_angle
from instrument.iso9283._errors import ISO9283Error


@dataclass(frozen=True)
class CommandPath:
    """Calculation points on a commanded path.

    Attributes
    ----------
    points : (m, 3) array
        C_i, m.
    tangents : (m, 3) array
        Unit tangent of the commanded path at C_i (the normal of the cutting plane).
    orientations : (m, 3) array or None
        Commanded a, b, c at C_i, rad (None: orientation characteristics are not computed).
    """

    points: np.ndarray
    tangents: np.ndarray
    orientations: np.ndarray | None = None

    def __post_init__(self) -> None:
        points = np.asarray(self.points, dtype=float)
        tangents = np.asarray(self.tangents, dtype=float)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) < 1 or tangents.shape != points.shape:
            raise ISO9283Error(
                f"CommandPath: points and tangents must both be (m, 3) arrays, got {points.shape} and {tangents.shape}"
            )
        norms = np.linalg.norm(tangents, axis=1)
        if not (np.all(np.isfinite(points)) and np.all(norms > 0)):
            raise ISO9283Error("CommandPath: points must be finite and tangents non-zero")
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "tangents", tangents / norms[:, None])
        if self.orientations is not None:
            orientations = np.broadcast_to(np.asarray(self.orientations, dtype=float), points.shape).copy()
            object.__setattr__(self, "orientations", orientations)


def _orientations(orientation, count: int) -> np.ndarray | None:
    if orientation is None:
        return None
    array = np.asarray(orientation, dtype=float)
    if array.shape not in ((3,), (count, 3)) or not np.all(np.isfinite(array)):
        raise ISO9283Error(f"orientation: expected [a, b, c] or one row per point ({count}, 3), rad")
    return np.broadcast_to(array, (count, 3)).copy()


def linear_path(start, end, points: int = 50, *, orientation=None, margin: float = 0.1) -> CommandPath:
    """Calculation points evenly spread along a straight commanded path.

    Parameters
    ----------
    start, end : (3,) arrays
        The commanded segment, m.
    points : int
        m, the number of calculation points.
    orientation : (3,) or (points, 3) array, optional
        Commanded a, b, c, rad.
    margin : float
        Share of the length left out at each end (acceleration and deceleration are not part of
        the path characteristics), 0 ≤ margin < 0.5.
    """
    a, b = np.asarray(start, dtype=float).reshape(-1), np.asarray(end, dtype=float).reshape(-1)
    if a.shape != (3,) or b.shape != (3,) or np.linalg.norm(b - a) == 0.0:
        raise ISO9283Error("linear_path: start and end must be two different (3,) points")
    if not (0.0 <= margin < 0.5) or points < 1:
        raise ISO9283Error(f"linear_path: need points ≥ 1 and 0 ≤ margin < 0.5, got {points}, {margin}")
    s = np.linspace(margin, 1.0 - margin, points)
    tangent = (b - a) / np.linalg.norm(b - a)
    return CommandPath(a + s[:, None] * (b - a), np.tile(tangent, (points, 1)), _orientations(orientation, points))


def circular_path(center, radius: float, normal, start_direction, points: int = 72, *, sweep: float = 2 * np.pi,
                  orientation=None) -> CommandPath:
    """Calculation points on a commanded circle (or arc), counter-clockwise about ``normal``.

    Parameters
    ----------
    center : (3,) array
        m.
    radius : float
        m.
    normal : (3,) array
        Axis of the circle; the path turns counter-clockwise seen from its tip.
    start_direction : (3,) array
        Direction from the centre to the first point (projected into the circle's plane).
    points : int
        Calculation points, spread evenly over ``sweep`` (a full circle leaves out the end point,
        which would repeat the first).
    sweep : float
        rad.
    orientation : (3,) or (points, 3) array, optional
        Commanded a, b, c, rad.
    """
    c = np.asarray(center, dtype=float).reshape(-1)
    n = np.asarray(normal, dtype=float).reshape(-1)
    d = np.asarray(start_direction, dtype=float).reshape(-1)
    if c.shape != (3,) or n.shape != (3,) or d.shape != (3,) or not radius > 0 or points < 1:
        raise ISO9283Error("circular_path: center, normal, start_direction must be (3,), radius > 0, points ≥ 1")
    n = n / np.linalg.norm(n)
    d = d - (d @ n) * n
    if np.linalg.norm(d) < 1e-12:
        raise ISO9283Error("circular_path: start_direction is parallel to the normal")
    e1 = d / np.linalg.norm(d)
    e2 = np.cross(n, e1)
    full = abs(abs(sweep) - 2 * np.pi) < 1e-12
    phi = np.linspace(0.0, sweep, points, endpoint=not full)
    radial = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
    tangent = np.sign(sweep) * (-np.sin(phi)[:, None] * e1 + np.cos(phi)[:, None] * e2)
    return CommandPath(c + radius * radial, tangent, _orientations(orientation, points))


@dataclass(frozen=True)
class PathCharacteristics:
    """Path accuracy AT and path repeatability RT over n cycles (ISO 9283 8.2, 8.3).

    Attributes
    ----------
    at_p : float
        m, max over the calculation points of |barycentre of the n cut points − C_i|.
    at_a, at_b, at_c : float
        rad, max over the points of |mean attained angle − commanded angle| (NaN without orientations).
    rt_p : float
        m, max over the points of RT_l,i = l̄_i + 3·S_l,i (l the distances of the cut points from
        their barycentre).
    rt_a, rt_b, rt_c : float
        rad, max over the points of 3·S of the angle (NaN without orientations).
    n, m : int
        Cycles and calculation points.
    barycentres : (m, 3) array
    deviation : (m,) array
        m, |barycentre − C_i| per point (the AT_p profile along the path).
    rt_l : (m,) array
        m, RT_l,i per point.
    cuts : (n, m, k) array
        The interpolated cut points, k = 3 or 6 columns as the attained paths.
    """

    at_p: float
    at_a: float
    at_b: float
    at_c: float
    rt_p: float
    rt_a: float
    rt_b: float
    rt_c: float
    n: int
    m: int
    barycentres: np.ndarray
    deviation: np.ndarray
    rt_l: np.ndarray
    cuts: np.ndarray


def _attained(path, name: str) -> np.ndarray:
    try:
        array = np.array(path, dtype=float)
    except (TypeError, ValueError):
        raise ISO9283Error(f"{name}: expected an (N, 3) or (N, 6) array of attained poses") from None
    if array.ndim != 2 or array.shape[1] not in (3, 6) or len(array) < 2:
        raise ISO9283Error(f"{name}: expected an (N, 3) or (N, 6) array (N ≥ 2), got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        row = int(np.argwhere(~np.isfinite(array))[0][0])
        raise ISO9283Error(f"{name}: non-finite value at sample {row} (drop unmeasured samples)")
    if array.shape[1] == 6:
        array[:, 3:] = np.unwrap(array[:, 3:], axis=0)
    return array


def _cut(path: np.ndarray, point: np.ndarray, tangent: np.ndarray) -> np.ndarray | None:
    """Where the polyline ``path`` crosses the plane through ``point`` normal to ``tangent``,
    interpolated; the crossing nearest to ``point`` if there are several; None if none."""
    side = (path[:, :3] - point) @ tangent
    crossing = np.flatnonzero((side[:-1] <= 0.0) & (side[1:] > 0.0) | (side[:-1] >= 0.0) & (side[1:] < 0.0))
    if len(crossing) == 0:
        return None
    first, second = side[crossing], side[crossing + 1]
    fraction = np.where(first == second, 0.0, first / np.where(first == second, 1.0, first - second))
    cuts = path[crossing] + fraction[:, None] * (path[crossing + 1] - path[crossing])
    return cuts[int(np.argmin(np.linalg.norm(cuts[:, :3] - point, axis=1)))]


def path_characteristics(
    command: CommandPath, paths: Sequence, *, max_distance: float | None = None
) -> PathCharacteristics:
    """Path accuracy AT_p, AT_a/b/c and repeatability RT_p, RT_a/b/c (ISO 9283 8.2, 8.3).

    Parameters
    ----------
    command : CommandPath
        The calculation points on the commanded path.
    paths : sequence of (N_j, 3) or (N_j, 6) arrays
        The attained path of each cycle (ISO 9283 asks for 10), samples in time order, m and rad
        ([x, y, z] or [x, y, z, a, b, c]); all with the same number of columns.
    max_distance : float, optional
        m; a cut farther than this from C_i is an error (the attained path missed that point).

    Returns
    -------
    PathCharacteristics

    Raises
    ------
    ISO9283Error
        Fewer than 2 paths, a malformed path, or a path that does not cross a calculation plane
        (within ``max_distance``); the message names the path and the point.
    """
    if not isinstance(command, CommandPath):
        raise ISO9283Error(
            f"command: expected a CommandPath (linear_path, circular_path), got {type(command).__name__}"
        )
    if isinstance(paths, np.ndarray) and paths.ndim == 2:
        raise ISO9283Error("paths: expected one array per cycle, got a single array")
    arrays = [_attained(p, f"paths[{j}]") for j, p in enumerate(paths)]
    if len(arrays) < 2:
        raise ISO9283Error(f"paths: needs at least 2 cycles, got {len(arrays)}")
    columns = {a.shape[1] for a in arrays}
    if len(columns) != 1:
        raise ISO9283Error("paths: all cycles must have the same columns (all [x, y, z] or all [x, y, z, a, b, c])")
    width = columns.pop()
    m = len(command.points)
    cuts = np.empty((len(arrays), m, width))
    for j, path in enumerate(arrays):
        for i in range(m):
            cut = _cut(path, command.points[i], command.tangents[i])
            if cut is None:
                raise ISO9283Error(f"paths[{j}]: never crosses the plane normal to the command path at point {i}")
            gap = float(np.linalg.norm(cut[:3] - command.points[i]))
            if max_distance is not None and gap > max_distance:
                raise ISO9283Error(
                    f"paths[{j}]: crosses the plane at point {i} {gap * 1e3:.3f} mm from the command path "
                    f"(max_distance {max_distance * 1e3:.3f} mm)"
                )
            cuts[j, i] = cut
    barycentres = cuts[:, :, :3].mean(axis=0)
    deviation = np.linalg.norm(barycentres - command.points, axis=1)
    distances = np.linalg.norm(cuts[:, :, :3] - barycentres[None], axis=2)  # (n, m)
    rt_l = distances.mean(axis=0) + 3.0 * distances.std(axis=0, ddof=1)
    at_angles = rt_angles = np.full(3, np.nan)
    if width == 6 and command.orientations is not None:
        angles = cuts[:, :, 3:]
        # one branch per point across the cycles, about the commanded angle
        angles = command.orientations[None] + wrap_angle(angles - command.orientations[None])
        at_angles = np.abs(wrap_angle(angles.mean(axis=0) - command.orientations)).max(axis=0)
        rt_angles = (3.0 * angles.std(axis=0, ddof=1)).max(axis=0)
    elif width == 6:
        angles = cuts[:, :, 3:]
        angles = angles[0][None] + wrap_angle(angles - angles[0][None])
        rt_angles = (3.0 * angles.std(axis=0, ddof=1)).max(axis=0)
    return PathCharacteristics(
        at_p=float(deviation.max()),
        at_a=float(at_angles[0]),
        at_b=float(at_angles[1]),
        at_c=float(at_angles[2]),
        rt_p=float(rt_l.max()),
        rt_a=float(rt_angles[0]),
        rt_b=float(rt_angles[1]),
        rt_c=float(rt_angles[2]),
        n=len(arrays),
        m=m,
        barycentres=barycentres,
        deviation=deviation,
        rt_l=rt_l,
        cuts=cuts,
    )


@dataclass(frozen=True)
class CornerDeviation:
    """Cornering round-off error CR and cornering overshoot CO (ISO 9283 8.5).

    Attributes
    ----------
    cr, co : float
        m, the largest over the cycles.
    cr_cycles, co_cycles : (n,) arrays
        m, per cycle: CR = least distance from the commanded corner point to the attained path;
        CO = largest deviation of the attained path, after its closest approach to the corner,
        beyond the second segment's line to the outside of the corner (0 if it stays inside).
    """

    cr: float
    co: float
    cr_cycles: np.ndarray
    co_cycles: np.ndarray


def _segment_distance(path: np.ndarray, point: np.ndarray) -> tuple[float, int]:
    """Least distance from ``point`` to the polyline, and the index of the segment it lies on."""
    a, b = path[:-1], path[1:]
    span = b - a
    length2 = np.einsum("ij,ij->i", span, span)
    f = np.clip(np.einsum("ij,ij->i", point - a, span) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
    gaps = np.linalg.norm(a + f[:, None] * span - point, axis=1)
    k = int(np.argmin(gaps))
    return float(gaps[k]), k


def corner_deviation(corner, incoming, outgoing, paths: Sequence) -> CornerDeviation:
    """Cornering deviations CR and CO at a sharp commanded corner (ISO 9283 8.5).

    Parameters
    ----------
    corner : (3,) array
        The commanded corner point, m.
    incoming : (3,) array
        Direction of the first commanded segment (toward the corner).
    outgoing : (3,) array
        Direction of the second commanded segment (away from the corner); not parallel to ``incoming``.
    paths : sequence of (N_j, 3) arrays (or (N_j, 6): the positions are used)
        The attained path through the corner in each cycle (ISO 9283 asks for 3), in time order.

    Returns
    -------
    CornerDeviation
    """
    point = np.asarray(corner, dtype=float).reshape(-1)
    d1 = np.asarray(incoming, dtype=float).reshape(-1)
    d2 = np.asarray(outgoing, dtype=float).reshape(-1)
    if point.shape != (3,) or d1.shape != (3,) or d2.shape != (3,):
        raise ISO9283Error("corner, incoming, outgoing: expected (3,) arrays")
    d1, d2 = d1 / np.linalg.norm(d1), d2 / np.linalg.norm(d2)
    outside = d1 - (d1 @ d2) * d2  # across the second segment, toward where the first one was heading
    if np.linalg.norm(outside) < 1e-9:
        raise ISO9283Error("incoming and outgoing: the segments are parallel, there is no corner")
    outside /= np.linalg.norm(outside)
    if isinstance(paths, np.ndarray) and paths.ndim == 2:
        raise ISO9283Error("paths: expected one array per cycle, got a single array")
    arrays = [_attained(p, f"paths[{j}]")[:, :3] for j, p in enumerate(paths)]
    if not arrays:
        raise ISO9283Error("paths: needs at least one cycle")
    cr, co = [], []
    for path in arrays:
        gap, k = _segment_distance(path, point)
        cr.append(gap)
        co.append(max(0.0, float(((path[k:] - point) @ outside).max())))
    return CornerDeviation(float(max(cr)), float(max(co)), np.array(cr), np.array(co))


@dataclass(frozen=True)
class PathVelocity:
    """Path velocity accuracy AV, repeatability RV and fluctuation FV (ISO 9283 8.6).

    Attributes
    ----------
    av : float
        (v̄ − v_c)/v_c, a fraction (× 100 for the standard's %), v̄ the mean of the cycles' means.
    rv : float
        3·S_v/v_c, a fraction (read as ±), S_v the standard deviation of the cycles' mean speeds.
    fv : float
        m/s, the largest over the cycles of (highest − lowest speed) within one cycle.
    mean_speed : float
        m/s, v̄.
    cycle_means : (n,) array
        m/s.
    commanded : float
        m/s, v_c.
    """

    av: float
    rv: float
    fv: float
    mean_speed: float
    cycle_means: np.ndarray
    commanded: float


def path_speed(t, positions, *, window: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Speed along a measured path: (times, speeds) in s and m/s.

    ``window`` None: central differences of neighbouring samples (interior samples). A window w
    (s): |p(t + w/2) − p(t − w/2)| / w at the samples where both ends lie in the record, positions
    interpolated linearly — a moving chord that averages the measurement noise down by about the
    number of samples it spans.
    """
    times = np.asarray(t, dtype=float)
    points = np.asarray(positions, dtype=float)
    if times.ndim != 1 or points.shape != (len(times), 3) or len(times) < 3:
        raise ISO9283Error(f"t, positions: expected (N,) and (N, 3) with N ≥ 3, got {times.shape}, {points.shape}")
    if np.any(np.diff(times) <= 0.0) or not np.all(np.isfinite(points)):
        raise ISO9283Error("t must increase strictly and positions be finite")
    if window is None:
        speeds = np.linalg.norm(points[2:] - points[:-2], axis=1) / (times[2:] - times[:-2])
        return times[1:-1], speeds
    half = 0.5 * float(window)
    if not half > 0:
        raise ISO9283Error(f"window: must be a positive time, got {window!r}")
    inside = (times - half >= times[0]) & (times + half <= times[-1])
    if np.count_nonzero(inside) < 1:
        raise ISO9283Error(f"window: {window} s is longer than the record")
    centre = times[inside]
    ahead = np.column_stack([np.interp(centre + half, times, points[:, k]) for k in range(3)])
    behind = np.column_stack([np.interp(centre - half, times, points[:, k]) for k in range(3)])
    return centre, np.linalg.norm(ahead - behind, axis=1) / (2.0 * half)


def path_velocity(cycles: Sequence, commanded_speed: float, *, window: float | None = None) -> PathVelocity:
    """Path velocity characteristics AV, RV, FV over n cycles (ISO 9283 8.6).

    Parameters
    ----------
    cycles : sequence of (t, positions)
        Per cycle, the part of the path travelled at the commanded speed (ISO 9283 asks for 10
        cycles; acceleration and deceleration left out by the caller), s and m.
    commanded_speed : float
        v_c, m/s.
    window : float, optional
        s, the chord of :func:`path_speed` (None: neighbouring samples).

    Returns
    -------
    PathVelocity
    """
    v_c = float(commanded_speed)
    if not (np.isfinite(v_c) and v_c > 0):
        raise ISO9283Error(f"commanded_speed: must be a positive speed (m/s), got {commanded_speed!r}")
    if len(cycles) < 2:
        raise ISO9283Error(f"cycles: needs at least 2 cycles, got {len(cycles)}")
    means, spans = [], []
    for j, cycle in enumerate(cycles):
        try:
            t, positions = cycle
        except (TypeError, ValueError):
            raise ISO9283Error(f"cycles[{j}]: expected a (t, positions) pair") from None
        _, speeds = path_speed(t, positions, window=window)
        means.append(float(speeds.mean()))
        spans.append(float(speeds.max() - speeds.min()))
    cycle_means = np.array(means)
    v_bar = float(cycle_means.mean())
    return PathVelocity(
        av=(v_bar - v_c) / v_c,
        rv=3.0 * float(cycle_means.std(ddof=1)) / v_c,
        fv=max(spans),
        mean_speed=v_bar,
        cycle_means=cycle_means,
        commanded=v_c,
    )
