"""The optical bench: the sensor module's screens and cameras, and the OPR's lasers, true and nominal.

Everything here is the *truth* the renderer images, drawn once from a seeded stream
(``world.rng("optics")``), next to the *nominal* values a station file claims
(``nominal_geometry()``). The differences are the residual errors of a real build: a screen
mounted a millimetre off its drawing distance and a tenth of a degree tilted, a camera calibration
with a few 1e-4 of scale error, a little skew and uncorrected radial distortion, laser fans that are
not exactly perpendicular. Together they put the uncompensated instrument tens of micrometres and
tens of arc-seconds off over the calibration ranges, like the reference paper (±0.08 mm, ±40″).

Conventions (shared with the station file, see method.md §3)
-------------------------------------------------------------
- Screen k is nominally the plane ``e_k · p = l`` (l = 0.25 m) in M, with 2-D axes
  x: (u, v) = (y, z), y: (z, x), z: (x, y), so ``u × v = +e_k``.
- The screen's (u, v) **origin is where the beam of an OPR sitting at M's origin meets it**, i.e.
  nominally ``l·e_k``: the cross sits at (0, 0) at the reference pose, and a displacement of
  0–70 mm along M's axes moves the crosses to 0–70 mm in u or v.
- Each camera sees a 1024 × 1040 (width × height) Mono8 image of ~160 mm of screen
  (0.156 mm/px) centred on (u, v) = (35, 35) mm, so the view spans about −45…+115 mm in u and v:
  the whole 0–70 mm calibration range plus ±1° of tilt (±4.4 mm at 0.25 m) with ≥ 30 mm margin.
- Image points: x = column, y = row, pixel centres on integers; ``pixel_to_screen`` maps
  (x, y, 1) → (u, v, 1) in metres. A camera behind a translucent screen sees it mirrored
  (determinant < 0); cameras may be mounted turned (here y by 90°, z by 180°).

The camera's TRUE model, screen → pixel: the inverse of a true homography (the nominal one with
scale, anisotropy, skew, rotation, offset and perspective errors), then radial distortion about a
centre near the image centre, ``p_d = c + (p − c)·(1 + k1·ρ² + k2·ρ⁴)``, ρ = |p − c| / r_norm.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from sim_devices._config import checked_fields
from sim_devices._transforms import ARCSEC, rotvec_to_matrix

AXIS_NAMES = ("x", "y", "z")
_AXIS = {"x": 0, "y": 1, "z": 2}
# Nominal 2-D screen axes in M: (u, v) for each screen, u × v = +e_k.
_NOMINAL_UV = {
    "x": (np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])),
    "y": (np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])),
    "z": (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])),
}
# The two fans of emitter k contain the beam e_k and one other OPR axis; a fan's normal is the
# third axis. Fan names say which two axes it contains.
FANS = {"x": ("xy", "xz"), "y": ("yz", "yx"), "z": ("zx", "zy")}
_FAN_NORMAL_AXIS = {"xy": 2, "xz": 1, "yz": 0, "yx": 2, "zx": 1, "zy": 0}


@dataclass
class CameraMount:
    """How a camera looks at its screen: mirrored (from behind a translucent screen) and turned."""

    mirrored: bool = True
    turn_deg: float = 0.0


@dataclass
class OpticsConfig:
    """Nominal design values and the spread of the true ones around them (SI units)."""

    screen_distance: float = 0.25  # l, m
    size_px: tuple[int, int] = (1024, 1040)  # width, height (pylon emulator default)
    metres_per_px: float = 0.156e-3
    view_centre: tuple[float, float] = (0.035, 0.035)  # screen (u, v) at the image centre, m
    cameras: dict[str, CameraMount] = field(
        default_factory=lambda: {
            "x": CameraMount(mirrored=True, turn_deg=0.0),
            "y": CameraMount(mirrored=True, turn_deg=90.0),
            "z": CameraMount(mirrored=False, turn_deg=180.0),
        }
    )
    # screens (true vs nominal)
    screen_distance_std: float = 1.5e-3  # the drawing's distance vs the built one
    screen_offset_std: float = 20e-6  # in-plane position of the (u, v) origin
    screen_tilt_std: float = float(np.radians(0.1))  # out of plane
    screen_twist_std: float = 6 * ARCSEC  # about the normal
    # cameras: residual errors of the nominal pixel → screen calibration
    scale_error_std: float = 4e-4
    anisotropy_std: float = 2e-4
    skew_std: float = 1e-4  # rad
    rotation_error_std: float = 5 * ARCSEC
    offset_error_std: float = 15e-6  # m on the screen
    perspective_std: float = 3e-7  # 1/px: relative scale change per pixel across the field
    distortion_k1_range: tuple[float, float] = (2e-4, 5e-4)  # |k1|, sign random; ρ = r / r_norm
    distortion_k2_std: float = 5e-5
    distortion_r_norm_px: float = 700.0
    distortion_centre_std_px: float = 8.0
    # OPR lasers (true properties of the emitters)
    beam_tilt_std: float = 8 * ARCSEC
    fan_nonperpendicularity_std: float = 10 * ARCSEC
    emitter_roll_std: float = 5 * ARCSEC
    emitter_offset_std: float = 10e-6
    stripe_sigma: float = 0.31e-3  # m on the screen (≈ 2 px)
    stripe_sigma_spread: float = 0.05  # relative, per emitter
    peak_level: float = 170.0  # grey levels (8-bit) of one stripe's peak at distance l
    peak_level_spread: float = 0.08  # relative, per fan
    fan_half_angle: float = float(np.radians(45.0))  # intensity 1/e² point along the fan
    # sensor
    background_level: float = 6.0  # grey levels (8-bit scale)
    vignetting: float = 0.25  # relative background drop at the corners
    read_noise: float = 1.2  # grey levels (8-bit scale), rms
    conversion_gain: float = 0.025  # grey levels per photo-electron (8-bit scale): shot noise
    speckle_contrast: float = 0.08
    speckle_grain_px: float = 3.0

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> OpticsConfig:
        data = checked_fields(cls, data, "optics config")
        if "cameras" in data:
            data["cameras"] = {
                k: v
                if isinstance(v, CameraMount)
                else CameraMount(**checked_fields(CameraMount, v, f"optics config cameras.{k}"))
                for k, v in dict(data["cameras"]).items()
            }
            missing = set(AXIS_NAMES) - set(data["cameras"])
            if missing:
                raise ValueError(f"optics config: cameras lacks {sorted(missing)}")
        for key in ("size_px", "view_centre", "distortion_k1_range"):
            if key in data:
                data[key] = tuple(data[key])
        return cls(**data)


@dataclass(frozen=True)
class Screen:
    """A screen plane in M: point = origin + u·a + v·b for screen coordinates (a, b) in metres."""

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.u, self.v)

    def to_m(self, uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, dtype=float)
        return self.origin + uv[..., :1] * self.u + uv[..., 1:2] * self.v


@dataclass(frozen=True)
class CameraModel:
    """One camera's true imaging of its screen (see the module docstring)."""

    size_px: tuple[int, int]
    pixel_to_screen_h: np.ndarray  # 3×3, undistorted pixel → true screen (u, v)
    k1: float
    k2: float
    distortion_centre: np.ndarray  # px
    r_norm: float

    def screen_to_pixel(self, uv: np.ndarray) -> np.ndarray:
        """True screen coordinates (..., 2) m → distorted image points (..., 2) px."""
        uv = np.asarray(uv, dtype=float)
        h = np.linalg.inv(self.pixel_to_screen_h)
        x, y = _homography(h, uv[..., 0], uv[..., 1])
        return np.stack(self._distort(x, y), -1)

    def pixel_to_screen(self, xy: np.ndarray) -> np.ndarray:
        """Distorted image points (..., 2) px → true screen coordinates (..., 2) m."""
        xy = np.asarray(xy, dtype=float)
        x, y = self._undistort(xy[..., 0], xy[..., 1])
        return np.stack(_homography(self.pixel_to_screen_h, x, y), -1)

    def _distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cx, cy = self.distortion_centre
        dx, dy = x - cx, y - cy
        rho2 = (dx * dx + dy * dy) / self.r_norm**2
        factor = 1.0 + self.k1 * rho2 + self.k2 * rho2 * rho2
        return cx + dx * factor, cy + dy * factor

    def _undistort(self, x_d: np.ndarray, y_d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # Fixed-point iteration: the distortion is < 1 px and its slope ~1e-3, so each step gains
        # about three decimal digits; four steps reach ~1e-12 px.
        cx, cy = self.distortion_centre
        dx_d, dy_d = x_d - cx, y_d - cy
        dx, dy = dx_d, dy_d
        inv_norm2 = 1.0 / self.r_norm**2
        for _ in range(4):
            rho2 = (dx * dx + dy * dy) * inv_norm2
            factor = 1.0 + self.k1 * rho2 + self.k2 * rho2 * rho2
            dx, dy = dx_d / factor, dy_d / factor
        return cx + dx, cy + dy


def _homography(h: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    return (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w, (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w


@dataclass(frozen=True)
class Emitter:
    """One cross-line laser of the OPR, in the OPR frame O."""

    name: str
    offset: np.ndarray  # where its fans cross, in O (nominally the origin)
    beam: np.ndarray  # unit beam direction in O (nominally e_k)
    fan_normals: dict[str, np.ndarray]  # fan name → unit normal in O
    fan_peak_levels: dict[str, float]  # fan name → peak grey level at distance l
    stripe_sigma: float  # m on the screen

    def fan_planes_in_m(self, opr_in_m: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Fan name → (point, unit normal) in M for the OPR pose ``T_M_O``."""
        rotation, translation = opr_in_m[:3, :3], opr_in_m[:3, 3]
        point = rotation @ self.offset + translation
        return {fan: (point, rotation @ normal) for fan, normal in self.fan_normals.items()}


class OpticalBench:
    """Sensor module (three screens + cameras) and OPR lasers, true and nominal.

    Parameters
    ----------
    world : sim_devices.world.World
        Supplies the seeded stream ``world.rng("optics")``.
    config : OpticsConfig or mapping, optional
        Design values and spreads; see ``OpticsConfig``.
    """

    def __init__(self, world: Any, config: OpticsConfig | Mapping[str, Any] | None = None) -> None:
        self.config = config if isinstance(config, OpticsConfig) else OpticsConfig.from_dict(config)
        cfg = self.config
        rng = world.rng("optics")
        self.nominal_screens: dict[str, Screen] = {}
        self.screens: dict[str, Screen] = {}
        self.nominal_pixel_to_screen: dict[str, np.ndarray] = {}
        self.cameras: dict[str, CameraModel] = {}
        self.emitters: dict[str, Emitter] = {}
        for name in AXIS_NAMES:
            nominal = _nominal_screen(name, cfg.screen_distance)
            self.nominal_screens[name] = nominal
            self.screens[name] = _perturb_screen(nominal, rng, cfg)
            self.nominal_pixel_to_screen[name] = _nominal_homography(cfg, cfg.cameras[name])
            self.cameras[name] = _true_camera(self.nominal_pixel_to_screen[name], rng, cfg)
        for name in AXIS_NAMES:
            self.emitters[name] = _true_emitter(name, rng, cfg)

    # ------------------------------------------------------------------ station file
    def nominal_geometry(self) -> dict[str, Any]:
        """The ``geometry`` mapping of the station file (``instrument.pose.Geometry.from_dict``):
        nominal screens and the nominal (distortion-free) pixel → screen homographies."""
        screens = {}
        for name in AXIS_NAMES:
            s = self.nominal_screens[name]
            screens[name] = {
                "origin": s.origin.tolist(),
                "u": s.u.tolist(),
                "v": s.v.tolist(),
                "pixel_to_screen": self.nominal_pixel_to_screen[name].tolist(),
                "size_px": list(self.config.size_px),
            }
        return {"screens": screens}

    def true_description(self) -> dict[str, Any]:
        """Every true constant (JSON-able), for the ground-truth log and for tests."""
        cfg = asdict(self.config)
        out: dict[str, Any] = {"config": cfg, "screens": {}, "cameras": {}, "emitters": {}}
        for name in AXIS_NAMES:
            s, cam, em = self.screens[name], self.cameras[name], self.emitters[name]
            out["screens"][name] = {"origin": s.origin.tolist(), "u": s.u.tolist(), "v": s.v.tolist()}
            out["cameras"][name] = {
                "size_px": list(cam.size_px),
                "pixel_to_screen_undistorted": cam.pixel_to_screen_h.tolist(),
                "k1": cam.k1,
                "k2": cam.k2,
                "distortion_centre_px": cam.distortion_centre.tolist(),
                "r_norm_px": cam.r_norm,
            }
            out["emitters"][name] = {
                "offset": em.offset.tolist(),
                "beam": em.beam.tolist(),
                "fan_normals": {k: v.tolist() for k, v in em.fan_normals.items()},
                "fan_peak_levels": dict(em.fan_peak_levels),
                "stripe_sigma": em.stripe_sigma,
            }
        return out


# ---------------------------------------------------------------------------------- construction
def _nominal_screen(name: str, distance: float) -> Screen:
    u, v = _NOMINAL_UV[name]
    origin = np.zeros(3)
    origin[_AXIS[name]] = distance
    return Screen(origin, u.copy(), v.copy())


def _perturb_screen(nominal: Screen, rng: np.random.Generator, cfg: OpticsConfig) -> Screen:
    # Tilt about u and v (out of plane), twist about the normal; then move the plane along its
    # normal (distance error) and the (u, v) origin within it.
    tilt_u, tilt_v = rng.normal(0.0, cfg.screen_tilt_std, 2)
    twist = rng.normal(0.0, cfg.screen_twist_std)
    rotation = rotvec_to_matrix(tilt_u * nominal.u + tilt_v * nominal.v + twist * nominal.normal)
    u, v = rotation @ nominal.u, rotation @ nominal.v
    shift = rng.normal(0.0, cfg.screen_distance_std) * nominal.normal
    shift += rng.normal(0.0, cfg.screen_offset_std) * u + rng.normal(0.0, cfg.screen_offset_std) * v
    return Screen(nominal.origin + shift, u, v)


def _centred(cfg: OpticsConfig) -> np.ndarray:
    """Homography taking pixel (x, y) to coordinates relative to the image centre."""
    width, height = cfg.size_px
    return np.array([[1.0, 0.0, -(width - 1) / 2.0], [0.0, 1.0, -(height - 1) / 2.0], [0.0, 0.0, 1.0]])


def _nominal_homography(cfg: OpticsConfig, mount: CameraMount) -> np.ndarray:
    """Nominal pixel → screen: scale, mirror, turn, and the image centre onto ``view_centre``."""
    turn = np.radians(mount.turn_deg)
    c, s = np.cos(turn), np.sin(turn)
    linear = cfg.metres_per_px * np.array([[c, -s], [s, c]]) @ np.diag([-1.0 if mount.mirrored else 1.0, 1.0])
    linear[np.abs(linear) < 1e-18] = 0.0  # exact zeros for 90°/180° turns
    h = np.eye(3)
    h[:2, :2] = linear
    h[:2, 2] = cfg.view_centre
    return h @ _centred(cfg)


def _true_camera(nominal_h: np.ndarray, rng: np.random.Generator, cfg: OpticsConfig) -> CameraModel:
    centred = _centred(cfg)
    nominal_linear = (nominal_h @ np.linalg.inv(centred))[:2, :2]
    scale = rng.normal(0.0, cfg.scale_error_std)
    aniso = rng.normal(0.0, cfg.anisotropy_std)
    skew = rng.normal(0.0, cfg.skew_std)
    rotation = rng.normal(0.0, cfg.rotation_error_std)
    error = np.array([[1.0 + scale + aniso, skew], [0.0, 1.0 + scale - aniso]])
    c, s = np.cos(rotation), np.sin(rotation)
    linear = np.array([[c, -s], [s, c]]) @ nominal_linear @ error
    h = np.eye(3)
    h[:2, :2] = linear
    h[:2, 2] = np.asarray(cfg.view_centre) + rng.normal(0.0, cfg.offset_error_std, 2)
    h[2, :2] = rng.normal(0.0, cfg.perspective_std, 2)  # the camera's axis not quite square to the screen
    k1 = float(rng.uniform(*cfg.distortion_k1_range) * rng.choice([-1.0, 1.0]))
    k2 = float(rng.normal(0.0, cfg.distortion_k2_std))
    width, height = cfg.size_px
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0]) + rng.normal(0.0, cfg.distortion_centre_std_px, 2)
    return CameraModel((int(width), int(height)), h @ centred, k1, k2, centre, cfg.distortion_r_norm_px)


def _true_emitter(name: str, rng: np.random.Generator, cfg: OpticsConfig) -> Emitter:
    k = _AXIS[name]
    # The whole emitter is tilted (beam tilt, about the two axes across the beam) and rolled
    # about its beam; then each fan is turned about the beam by ± half the non-perpendicularity.
    across = [i for i in range(3) if i != k]
    tilt = np.zeros(3)
    tilt[across] = rng.normal(0.0, cfg.beam_tilt_std, 2)
    tilt[k] = rng.normal(0.0, cfg.emitter_roll_std)
    emitter_rotation = rotvec_to_matrix(tilt)
    beam = emitter_rotation[:, k]
    nonperp = rng.normal(0.0, cfg.fan_nonperpendicularity_std)
    normals, levels = {}, {}
    for sign, fan in zip((0.5, -0.5), FANS[name]):
        nominal_normal = np.zeros(3)
        nominal_normal[_FAN_NORMAL_AXIS[fan]] = 1.0
        turn = rotvec_to_matrix(beam * sign * nonperp)
        normals[fan] = turn @ emitter_rotation @ nominal_normal
        levels[fan] = float(cfg.peak_level * (1.0 + rng.normal(0.0, cfg.peak_level_spread)))
    offset = rng.normal(0.0, cfg.emitter_offset_std, 3)
    sigma = float(cfg.stripe_sigma * (1.0 + rng.normal(0.0, cfg.stripe_sigma_spread)))
    return Emitter(name, offset, beam, normals, levels, sigma)


# A bench built exactly as drawn (an ``OpticsConfig`` override): no screen, camera-calibration or emitter
# errors, so a solved pose is the true one to the vision's noise. Tests and benchmarks that judge a
# measurement against the truth without a calibration use it.
IDEAL_OPTICS: dict[str, Any] = {
    "screen_distance_std": 0.0, "screen_offset_std": 0.0, "screen_tilt_std": 0.0, "screen_twist_std": 0.0,
    "scale_error_std": 0.0, "anisotropy_std": 0.0, "skew_std": 0.0, "rotation_error_std": 0.0,
    "offset_error_std": 0.0, "perspective_std": 0.0, "distortion_k1_range": [0.0, 0.0], "distortion_k2_std": 0.0,
    "distortion_centre_std_px": 0.0, "beam_tilt_std": 0.0, "fan_nonperpendicularity_std": 0.0,
    "emitter_roll_std": 0.0, "emitter_offset_std": 0.0,
}

__all__ = ["AXIS_NAMES", "IDEAL_OPTICS", "CameraModel", "CameraMount", "Emitter", "FANS", "OpticalBench",
           "OpticsConfig", "Screen"]
