"""Screen geometry: where the three screens sit in M and how each camera's pixels map onto them.

Loaded from the station file's ``geometry`` mapping::

    screens:
      x: {origin: [0.25, 0, 0], u: [0, 1, 0], v: [0, 0, 1],
          pixel_to_screen: [[...], [...], [...]],          # homography (x, y, 1) px → (u, v, 1) m
          distortion: {k1: 0.0, k2: 0.0, center_px: [cx, cy]},   # optional
          size_px: [1024, 1040]}                            # optional: [width, height]
      y: {origin: [0, 0.25, 0], u: [0, 0, 1], v: [1, 0, 0], ...}
      z: {origin: [0, 0, 0.25], u: [1, 0, 0], v: [0, 1, 0], ...}

Screen k is the plane through ``origin`` spanned by the orthonormal ``u``, ``v`` (frame M, metres);
a point with screen coordinates (a, b) is ``origin + a·u + b·v``. Nominally u × v = e_k, so that a
rotation about M's axis k turns the cross on screen k by the same positive angle.

Image points follow method.md §2: x = column, y = row, pixel centres on integers.

**Radial distortion** (optional) is corrected in pixel space before the homography: a measured
image point p_d becomes p = c + (p_d − c)·(1 + k1·r² + k2·r⁴), r = |p_d − c| in pixels (so k1 is
in px⁻², k2 in px⁻⁴) and c = ``center_px``. The homography then maps p to the screen.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from instrument.pose._errors import GeometryError

SCREEN_NAMES = ("x", "y", "z")
AXIS_INDEX = {"x": 0, "y": 1, "z": 2}
_UNIT_TOLERANCE = 1e-6


def _vector(value: Any, length: int, field_name: str) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise GeometryError(f"{field_name}: expected {length} numbers, got {value!r}") from None
    if array.shape != (length,):
        raise GeometryError(f"{field_name}: expected {length} numbers, got {value!r}")
    if not np.all(np.isfinite(array)):
        raise GeometryError(f"{field_name}: must be finite, got {array.tolist()}")
    return array


@dataclass(frozen=True)
class Distortion:
    """Radial distortion corrected in pixel space: p = c + (p_d − c)·(1 + k1·r² + k2·r⁴)."""

    k1: float = 0.0
    k2: float = 0.0
    center_px: tuple[float, float] = (0.0, 0.0)

    def undistort(self, points_px: np.ndarray) -> np.ndarray:
        """Measured (distorted) image points (N, 2) → corrected points (N, 2)."""
        c = np.asarray(self.center_px)
        d = points_px - c
        r2 = np.sum(d * d, axis=-1, keepdims=True)
        return c + d * (1.0 + self.k1 * r2 + self.k2 * r2 * r2)

    def distort(self, points_px: np.ndarray) -> np.ndarray:
        """Inverse of ``undistort`` (Newton on the radial scale), for synthesising images/lines."""
        c = np.asarray(self.center_px)
        d = np.asarray(points_px, dtype=float) - c
        rho2 = np.sum(d * d, axis=-1)
        scale = np.ones_like(rho2)  # p_d − c = scale·(p − c); solve scale·(1 + k1 s²ρ² + k2 s⁴ρ⁴) = 1
        for _ in range(50):
            s2 = scale * scale * rho2
            f = scale * (1.0 + self.k1 * s2 + self.k2 * s2 * s2) - 1.0
            df = 1.0 + 3.0 * self.k1 * s2 + 5.0 * self.k2 * s2 * s2
            step = f / df
            scale = scale - step
            if np.all(np.abs(step) < 1e-15):
                break
        return c + d * scale[..., None]


@dataclass(frozen=True)
class Screen:
    """One screen and its camera mapping. See the module docstring for the conventions."""

    name: str
    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    pixel_to_screen: np.ndarray
    distortion: Distortion | None = None
    size_px: tuple[int, int] | None = None
    screen_to_pixel: np.ndarray = field(init=False, repr=False, compare=False)
    cache: dict = field(init=False, repr=False, compare=False)  # derived values (nominal stripe directions)

    def __post_init__(self) -> None:
        object.__setattr__(self, "screen_to_pixel", np.linalg.inv(self.pixel_to_screen))
        object.__setattr__(self, "cache", {})

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.u, self.v)

    def pixels_to_screen(self, points_px) -> np.ndarray:
        """Image points (N, 2) px → screen coordinates (N, 2) m (distortion, then homography)."""
        p = np.atleast_2d(np.asarray(points_px, dtype=float))
        if self.distortion is not None:
            p = self.distortion.undistort(p)
        h = p @ self.pixel_to_screen[:, :2].T + self.pixel_to_screen[:, 2]
        return h[:, :2] / h[:, 2:3]

    def screen_to_pixels(self, points_uv) -> np.ndarray:
        """Screen coordinates (N, 2) m → image points (N, 2) px (inverse homography, then distortion)."""
        q = np.atleast_2d(np.asarray(points_uv, dtype=float))
        h = np.column_stack([q, np.ones(len(q))]) @ self.screen_to_pixel.T
        p = h[:, :2] / h[:, 2:3]
        if self.distortion is not None:
            p = self.distortion.distort(p)
        return p

    def to_frame(self, points_uv) -> np.ndarray:
        """Screen coordinates (N, 2) → points in M (N, 3)."""
        q = np.atleast_2d(np.asarray(points_uv, dtype=float))
        return self.origin + q[:, :1] * self.u + q[:, 1:2] * self.v

    def contains_pixel(self, point_px) -> bool:
        """True when the point lies on the sensor (always True when ``size_px`` is unknown)."""
        if self.size_px is None:
            return True
        x, y = point_px
        width, height = self.size_px
        return bool(-0.5 <= x <= width - 0.5 and -0.5 <= y <= height - 0.5)

    # ------------------------------------------------------------------ (de)serialisation
    @classmethod
    def from_dict(cls, name: str, data: Mapping[str, Any]) -> Screen:
        where = f"screens.{name}"
        if not isinstance(data, Mapping):
            raise GeometryError(f"{where}: expected a mapping, got {type(data).__name__}")
        known = {"origin", "u", "v", "pixel_to_screen", "distortion", "size_px"}
        unknown = set(data) - known
        if unknown:
            raise GeometryError(f"{where}: unknown field(s) {sorted(unknown)}; expected {sorted(known)}")
        for required in ("origin", "u", "v", "pixel_to_screen"):
            if required not in data:
                raise GeometryError(f"{where}.{required}: missing")
        origin = _vector(data["origin"], 3, f"{where}.origin")
        u = _vector(data["u"], 3, f"{where}.u")
        v = _vector(data["v"], 3, f"{where}.v")
        for axis_name, axis in (("u", u), ("v", v)):
            if abs(np.linalg.norm(axis) - 1.0) > _UNIT_TOLERANCE:
                raise GeometryError(
                    f"{where}.{axis_name}: must be a unit vector, got {axis.tolist()} (norm {np.linalg.norm(axis):.9g})"
                )
        if abs(float(u @ v)) > _UNIT_TOLERANCE:
            raise GeometryError(f"{where}.v: must be perpendicular to u, got u·v = {float(u @ v):.3g}")
        axis = np.zeros(3)
        axis[AXIS_INDEX[name]] = 1.0
        normal = np.cross(u, v)
        facing = float(normal @ axis)
        # The contract: screen k is (nominally) perpendicular to M's axis k, in front of the OPR,
        # with u × v along +e_k. A screen entered under the wrong name fails here, not in the solver.
        if facing < np.cos(np.radians(30.0)):
            raise GeometryError(
                f"{where}: u × v = {normal.round(6).tolist()} must point along +{name} (within 30°); "
                f"check the screen name and the order of u and v"
            )
        if float(origin @ axis) <= 0.0:
            raise GeometryError(f"{where}.origin: the screen must lie on the +{name} side of M, got {origin.tolist()}")
        try:
            homography = np.asarray(data["pixel_to_screen"], dtype=float)
        except (TypeError, ValueError):
            raise GeometryError(f"{where}.pixel_to_screen: expected a 3×3 matrix of numbers") from None
        if homography.shape != (3, 3) or not np.all(np.isfinite(homography)):
            raise GeometryError(f"{where}.pixel_to_screen: expected a finite 3×3 matrix, got shape {homography.shape}")
        singular = np.linalg.svd(homography, compute_uv=False)
        if singular[-1] <= 1e-12 * singular[0]:
            raise GeometryError(f"{where}.pixel_to_screen: singular homography (singular values {singular.tolist()})")
        distortion = None
        if data.get("distortion") is not None:
            dist = data["distortion"]
            if not isinstance(dist, Mapping):
                raise GeometryError(f"{where}.distortion: expected a mapping with k1, k2, center_px")
            unknown = set(dist) - {"k1", "k2", "center_px"}
            if unknown:
                raise GeometryError(
                    f"{where}.distortion: unknown field(s) {sorted(unknown)}; expected k1, k2, center_px"
                )
            if "center_px" not in dist:
                raise GeometryError(f"{where}.distortion.center_px: missing")
            k = {}
            for key in ("k1", "k2"):
                try:
                    k[key] = float(dist.get(key, 0.0))
                except (TypeError, ValueError):
                    raise GeometryError(f"{where}.distortion.{key}: expected a number, got {dist.get(key)!r}") from None
                if not np.isfinite(k[key]):
                    raise GeometryError(f"{where}.distortion.{key}: must be finite, got {k[key]}")
            center = _vector(dist["center_px"], 2, f"{where}.distortion.center_px")
            distortion = Distortion(k["k1"], k["k2"], (float(center[0]), float(center[1])))
        size = None
        if data.get("size_px") is not None:
            size_array = _vector(data["size_px"], 2, f"{where}.size_px")
            if np.any(size_array < 1) or np.any(size_array != np.round(size_array)):
                raise GeometryError(
                    f"{where}.size_px: expected [width, height] in whole pixels ≥ 1, got {data['size_px']!r}"
                )
            size = (int(size_array[0]), int(size_array[1]))
        return cls(name, origin, u, v, homography, distortion, size)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "origin": self.origin.tolist(),
            "u": self.u.tolist(),
            "v": self.v.tolist(),
            "pixel_to_screen": self.pixel_to_screen.tolist(),
        }
        if self.distortion is not None:
            out["distortion"] = {
                "k1": self.distortion.k1,
                "k2": self.distortion.k2,
                "center_px": list(self.distortion.center_px),
            }
        if self.size_px is not None:
            out["size_px"] = list(self.size_px)
        return out


@dataclass(frozen=True)
class Geometry:
    """The three screens, keyed "x", "y", "z"."""

    screens: Mapping[str, Screen]
    cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)  # derived arrays (solver)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Geometry:
        """Validate and load the station file's ``geometry`` mapping; errors name the field."""
        if not isinstance(data, Mapping) or "screens" not in data:
            raise GeometryError("screens: missing (geometry must be a mapping with a 'screens' entry)")
        unknown = set(data) - {"screens"}
        if unknown:
            raise GeometryError(f"geometry: unknown field(s) {sorted(unknown)}; expected 'screens'")
        screens = data["screens"]
        if not isinstance(screens, Mapping):
            raise GeometryError(f"screens: expected a mapping x/y/z, got {type(screens).__name__}")
        unknown = set(screens) - set(SCREEN_NAMES)
        if unknown:
            raise GeometryError(f"screens: unknown screen(s) {sorted(map(str, unknown))}; expected x, y, z")
        for name in SCREEN_NAMES:
            if name not in screens:
                raise GeometryError(f"screens.{name}: missing")
        return cls({name: Screen.from_dict(name, screens[name]) for name in SCREEN_NAMES})

    def to_dict(self) -> dict[str, Any]:
        return {"screens": {name: self.screens[name].to_dict() for name in SCREEN_NAMES}}


def make_homography(
    metres_per_pixel: float,
    image_center_px=(511.5, 519.5),
    screen_center=(0.0, 0.0),
    rotation: float = 0.0,
    mirrored: bool = False,
    perspective=(0.0, 0.0),
) -> np.ndarray:
    """A plausible pixel → screen homography (for tests, benchmarks and simulated stations).

    The image point ``image_center_px`` maps to ``screen_center``; the image axes are scaled by
    ``metres_per_pixel``, mirrored (x → −x) if ``mirrored`` (camera behind a translucent screen),
    turned by ``rotation`` rad, and tilted by the small projective terms ``perspective`` (px⁻¹).
    """
    c, s = np.cos(rotation), np.sin(rotation)
    linear = metres_per_pixel * np.array([[c, -s], [s, c]]) @ np.diag([-1.0 if mirrored else 1.0, 1.0])
    to_centered = np.array([[1.0, 0.0, -image_center_px[0]], [0.0, 1.0, -image_center_px[1]], [0.0, 0.0, 1.0]])
    affine = np.eye(3)
    affine[:2, :2] = linear
    affine[:2, 2] = screen_center
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [perspective[0], perspective[1], 1.0]])
    return affine @ tilt @ to_centered
