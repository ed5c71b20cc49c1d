"""Stripe lines on the screens: the exact forward model, and measured crosses mapped onto screens.

Fans are labelled by the two OPR axes they contain, emitter first: emitter x fans in "xy" and
"xz", emitter y in "yz" and "yx", emitter z in "zx" and "zy" (method.md §1). The fan "ka" has unit
normal R·e_j, j the third axis, and its stripe runs (nominally) along M's axis a on screen k.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from instrument.pose._errors import CrossOffScreenError, MissingScreenError, PoseError, StripeMatchError
from instrument.pose._geometry import AXIS_INDEX, SCREEN_NAMES, Geometry, Screen
from instrument.pose._rotation import Pose

# Per screen (= emitter) the two fans; FAN_AXES[fan] = (axis the stripe runs along, normal axis j).
FANS: dict[str, tuple[str, str]] = {"x": ("xy", "xz"), "y": ("yz", "yx"), "z": ("zx", "zy")}
FAN_AXES: dict[str, tuple[int, int]] = {
    fan: (AXIS_INDEX[fan[1]], 3 - AXIS_INDEX[fan[0]] - AXIS_INDEX[fan[1]]) for pair in FANS.values() for fan in pair
}
_MAX_MATCH_ANGLE = np.radians(40.0)
_MATCH_COSINE = float(np.cos(_MAX_MATCH_ANGLE))
_PARALLEL_COSINE = float(np.cos(np.radians(20.0)))
_IDENTITY, _ZERO = np.eye(3), np.zeros(3)
_DISTORTED_SAMPLES = np.linspace(-1.0, 1.0, 9)[:, None]


@dataclass(frozen=True)
class ScreenLine:
    """A stripe line in a screen's (u, v) coordinates, metres.

    Attributes
    ----------
    point : (2,) array
        A point on the line (for a measured stripe: the middle of the observed segment).
    direction : (2,) array
        Unit direction, oriented along the M axis the stripe nominally runs along.
    half_length : float
        Half the length of the observed segment, m (0 for a predicted line).
    """

    point: np.ndarray
    direction: np.ndarray
    half_length: float = 0.0

    def distance(self, points_uv) -> np.ndarray:
        """Signed perpendicular distance of points (N, 2) from the line, m."""
        d = np.atleast_2d(points_uv) - self.point
        return d[:, 0] * self.direction[1] - d[:, 1] * self.direction[0]


@dataclass(frozen=True)
class ScreenCross:
    """One measured cross on its screen: two stripe lines keyed by fan label, and the centre.

    ``center`` is the intersection of the two lines in (u, v) m; ``center_m`` the same point in M.
    """

    screen: str
    lines: Mapping[str, ScreenLine]
    center: np.ndarray
    center_m: np.ndarray


def _fan_line(rotation: np.ndarray, translation: np.ndarray, screen: Screen, fan: str) -> ScreenLine:
    """Exact intersection of the fan plane {P : m·(P − t) = 0} with the screen plane."""
    along, normal_axis = FAN_AXES[fan]
    m = rotation[:, normal_axis]
    n2 = np.array([m @ screen.u, m @ screen.v])  # m·(o + a·u + b·v − t) = 0 is n2·(a, b) = −c
    norm2 = float(n2 @ n2)
    if norm2 < 1e-12:
        raise PoseError(f"fan {fan!r} is parallel to screen {screen.name!r}: no stripe")
    c = float(m @ (screen.origin - translation))
    point = -c * n2 / norm2
    direction = np.array([n2[1], -n2[0]]) / np.sqrt(norm2)
    along_3d = direction[0] * screen.u + direction[1] * screen.v
    if along_3d @ rotation[:, along] < 0:  # orient along the OPR axis the fan contains
        direction = -direction
    return ScreenLine(point, direction, 0.0)


def predict_lines(pose: Pose, geometry: Geometry) -> dict[str, dict[str, ScreenLine]]:
    """The six stripe lines a pose puts on the screens (exact plane–plane intersections).

    Returns ``{screen: {fan: ScreenLine}}`` in each screen's (u, v) coordinates, metres; the
    direction of fan "ka" points along the OPR's axis a as seen on the screen.
    """
    rotation, translation = pose.rotation, pose.translation
    return {
        name: {fan: _fan_line(rotation, translation, geometry.screens[name], fan) for fan in FANS[name]}
        for name in SCREEN_NAMES
    }


def nominal_directions(screen: Screen) -> dict[str, np.ndarray]:
    """Each fan's stripe direction (u, v) on the screen at the identity rotation."""
    cached = screen.cache.get("nominal_directions")
    if cached is None:  # depends on the screen only: computed once per Screen
        cached = {fan: _fan_line(_IDENTITY, _ZERO, screen, fan).direction for fan in FANS[screen.name]}
        screen.cache["nominal_directions"] = cached
    return cached


def intersect(first: ScreenLine, second: ScreenLine) -> np.ndarray:
    """Intersection of two non-parallel 2-D lines."""
    (a, c), (b, d) = first.direction, -second.direction  # solve [a b; c d]·(s, s') = Δ by Cramer
    delta = second.point - first.point
    determinant = a * d - b * c
    if abs(determinant) < 1e-12:
        raise PoseError("intersecting two parallel stripe lines")
    return first.point + ((delta[0] * d - delta[1] * b) / determinant) * first.direction


def _finite_pair(value) -> tuple[float, float] | None:
    """(a, b) as floats when ``value`` is a finite pair of numbers, else None."""
    try:
        a, b = (float(c) for c in value)
    except (TypeError, ValueError):
        return None
    return (a, b) if math.isfinite(a) and math.isfinite(b) else None


def _homography_terms(screen: Screen) -> tuple[float, ...]:
    """The pixel → screen homography's nine entries as Python floats (cached per screen): two
    points per stripe are mapped faster in plain arithmetic than through small numpy arrays."""
    terms = screen.cache.get("homography_terms")
    if terms is None:
        terms = tuple(float(v) for v in screen.pixel_to_screen.ravel())
        screen.cache["homography_terms"] = terms
    return terms


def _stripe_to_screen(stripe, screen: Screen, label: str) -> tuple[float, float, float, float, float]:
    """One fitted image stripe → (point u, point v, direction u, direction v, half length) on the
    screen, metres: the segment the vision fitted, about one cross-section per pixel."""
    point, direction = _finite_pair(stripe.point), _finite_pair(stripe.direction)
    if point is None or direction is None:
        raise PoseError(f"screen {screen.name!r}: {label} stripe has a non-finite or malformed point/direction")
    norm = math.hypot(*direction)
    if norm < 1e-9:
        raise PoseError(f"screen {screen.name!r}: {label} stripe has a zero direction")
    half_px = max(float(stripe.sections), 2.0) / 2.0
    dx, dy = direction[0] / norm * half_px, direction[1] / norm * half_px
    horizon = f"screen {screen.name!r}: {label} stripe maps to infinity (beyond the homography's horizon)"
    if screen.distortion is None:  # a homography maps lines to lines exactly: two ends suffice
        h00, h01, h02, h10, h11, h12, h20, h21, h22 = _homography_terms(screen)
        ends = []
        for x, y in ((point[0] - dx, point[1] - dy), (point[0] + dx, point[1] + dy)):
            w = h20 * x + h21 * y + h22
            if abs(w) < 1e-300:
                raise PoseError(horizon)
            ends.append(((h00 * x + h01 * y + h02) / w, (h10 * x + h11 * y + h12) / w))
        (u0, v0), (u1, v1) = ends
        length = math.hypot(u1 - u0, v1 - v0)
        if not (math.isfinite(length) and length > 0.0):
            raise PoseError(horizon)
        return 0.5 * (u0 + u1), 0.5 * (v0 + v1), (u1 - u0) / length, (v1 - v0) / length, 0.5 * length
    uv = screen.pixels_to_screen(np.asarray(point) + _DISTORTED_SAMPLES * np.array([dx, dy]))
    if not math.isfinite(uv.sum()):
        raise PoseError(horizon)
    centroid = uv.mean(axis=0)
    _, _, vt = np.linalg.svd(uv - centroid)  # straight line through the slightly curved image
    along = (uv - centroid) @ vt[0]
    return float(centroid[0]), float(centroid[1]), float(vt[0][0]), float(vt[0][1]), float(np.ptp(along)) / 2.0


def _nominal_pairs(screen: Screen) -> tuple[tuple[float, float], tuple[float, float]]:
    cached = screen.cache.get("nominal_pairs")
    if cached is None:
        nominal = nominal_directions(screen)
        cached = tuple((float(nominal[fan][0]), float(nominal[fan][1])) for fan in FANS[screen.name])
        screen.cache["nominal_pairs"] = cached
    return cached


def observe_cross(measurement, screen: Screen) -> ScreenCross:
    """Map a ``CrossMeasurement`` (pixels) onto its screen and label its stripes by fan.

    Which stripe belongs to which fan is decided by direction on the screen, after the mapping,
    so a mirrored or turned camera changes nothing. Raises a ``PoseError`` subclass when the cross
    is off the image, the stripes are unusable, or they cannot be matched unambiguously.
    """
    name = screen.name
    center_px = _finite_pair(getattr(measurement, "center", None))
    if center_px is None:
        shown = np.asarray(getattr(measurement, "center", np.full(2, np.nan)), dtype=float).tolist()
        raise PoseError(f"screen {name!r}: cross centre is not a finite (x, y) pixel point: {shown}")
    if not screen.contains_pixel(center_px):
        width, height = screen.size_px or (0, 0)  # contains_pixel is False only with a known size
        raise CrossOffScreenError(
            f"screen {name!r}: cross centre ({center_px[0]:.1f}, {center_px[1]:.1f}) px is off the "
            f"{width}×{height} px image"
        )
    stripes = (
        _stripe_to_screen(measurement.horizontal, screen, "horizontal"),
        _stripe_to_screen(measurement.vertical, screen, "vertical"),
    )
    if abs(stripes[0][2] * stripes[1][2] + stripes[0][3] * stripes[1][3]) > _PARALLEL_COSINE:
        raise CrossOffScreenError(f"screen {name!r}: the two stripes are nearly parallel on the screen")
    nominal = _nominal_pairs(screen)
    cosines = [[s[2] * n[0] + s[3] * n[1] for n in nominal] for s in stripes]
    straight = abs(cosines[0][0]) + abs(cosines[1][1]) >= abs(cosines[0][1]) + abs(cosines[1][0])
    order = (0, 1) if straight else (1, 0)
    fans = FANS[name]
    lines: dict[str, ScreenLine] = {}
    oriented = []
    for fan_index, (stripe_index, fan) in enumerate(zip(order, fans)):
        pu, pv, du, dv, half_length = stripes[stripe_index]
        cosine = cosines[stripe_index][fan_index]
        if abs(cosine) < _MATCH_COSINE:
            raise StripeMatchError(
                f"screen {name!r}: stripe at {np.degrees(np.arccos(min(abs(cosine), 1.0))):.1f}° from fan "
                f"{fan!r}'s nominal direction; stripes can be matched to fans only within "
                f"{np.degrees(_MAX_MATCH_ANGLE):.0f}°"
            )
        sign = 1.0 if cosine > 0 else -1.0
        oriented.append((pu, pv, sign * du, sign * dv))
        lines[fan] = ScreenLine(np.array([pu, pv]), np.array([sign * du, sign * dv]), half_length)
    # the intersection of the two lines (Cramer's rule; not parallel: checked above)
    (p0u, p0v, d0u, d0v), (p1u, p1v, d1u, d1v) = oriented
    determinant = d1u * d0v - d0u * d1v
    along = ((p1u - p0u) * -d1v + (p1v - p0v) * d1u) / determinant
    cu, cv = p0u + along * d0u, p0v + along * d0v
    center_m = screen.origin + cu * screen.u + cv * screen.v
    return ScreenCross(name, lines, np.array([cu, cv]), center_m)


def observe_crosses(measurements: Mapping[str, object], geometry: Geometry) -> dict[str, ScreenCross]:
    """``observe_cross`` for the three screens; a missing screen raises ``MissingScreenError``."""
    if not isinstance(measurements, Mapping):
        raise PoseError(
            f"measurements: expected a mapping {{'x': ..., 'y': ..., 'z': ...}}, got {type(measurements).__name__}"
        )
    missing = [name for name in SCREEN_NAMES if measurements.get(name) is None]
    if missing:
        raise MissingScreenError(
            f"no cross measurement for screen(s) {', '.join(missing)} "
            f"(got {', '.join(sorted(map(str, measurements))) or 'none'}); "
            "all three crosses are needed for a 6-DOF pose"
        )
    unknown = set(measurements) - set(SCREEN_NAMES)
    if unknown:
        raise PoseError(f"measurements: unknown screen(s) {sorted(map(str, unknown))}; expected x, y, z")
    return {name: observe_cross(measurements[name], geometry.screens[name]) for name in SCREEN_NAMES}
