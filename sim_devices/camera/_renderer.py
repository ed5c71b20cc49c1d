"""Renders the three camera images of the crosses from the TRUE OPR pose and the TRUE optics.

Written independently of ``instrument`` (never imported): convention errors on either side then
fail tests instead of cancelling out.

Physics, per screen
-------------------
1. **Stripes**: each fan plane of the emitter cuts the (true) screen plane in a straight line. In
   the screen's own metric 2-D frame the line is exactly ``a·u + b·v + c = 0`` with
   ``(a, b) = (n·U, n·V)`` and ``c = n·(O − p)`` for the fan normal n through p and the screen
   origin O spanned by U, V. Only the fan's forward half (along the beam) lights the screen.
2. **Imaging**: the camera's true model maps pixel centres back onto the screen (undistort, then
   homography); the signed distance of each pixel centre from the line, divided by the local
   gradient of that distance in pixel space, is the perpendicular distance in pixels (first
   order in the local mapping, exact for σ of a few pixels).
3. **Profile**: a Gaussian of the stripe's width, integrated over the pixel's extent across the
   stripe, ``Φ((d + ½)/σ) − Φ((d − ½)/σ)`` (a 1-px box has the same second moment as the
   exact trapezoidal footprint of a square pixel at any angle, so the difference is 4th order).
   Its peak falls off as 1/r with the distance from the emitter and along the fan.
4. **Sensor**: background with vignetting and read + shot noise, multiplicative laser speckle (a smoothed random field
   with a grain of a few pixels), shot noise (variance ∝ signal), read noise, saturation,
   rounding to 8- or 12-bit grey levels. Noise is seeded per frame.

Only a band of ±6σ around each stripe is computed (about 4 % of a 1 MP frame), which keeps a
1024×1040 frame at a few tens of milliseconds and a 5 MP frame well under 1/3 s.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter, map_coordinates
from scipy.special import ndtr

from sim_devices.camera._optics import AXIS_NAMES, FANS, OpticalBench

_SQRT_2PI = float(np.sqrt(2.0 * np.pi))
_POOL_SLACK = 1 << 21  # extra normals in the background-noise pool: the range of window offsets


@dataclass(frozen=True)
class StripeOnScreen:
    """One fan's stripe on a true screen: the line ``normal · (u, v) + offset = 0`` (metres)."""

    fan: str
    normal: np.ndarray  # unit (2,) in the screen's (u, v)
    offset: float  # m
    emitter_point: np.ndarray  # fan origin in M
    beam: np.ndarray  # beam direction in M
    peak_level: float  # grey levels (8-bit scale) at distance l on the beam
    sigma: float  # m on the screen

    def distance(self, uv: np.ndarray) -> np.ndarray:
        """Signed distance (m) of screen points (..., 2) from the line."""
        return uv[..., 0] * self.normal[0] + uv[..., 1] * self.normal[1] + self.offset

    def point_and_direction(self) -> tuple[np.ndarray, np.ndarray]:
        return -self.offset * self.normal, np.array([-self.normal[1], self.normal[0]])


def stripes_on_screen(bench: OpticalBench, name: str, opr_in_m: np.ndarray) -> list[StripeOnScreen]:
    """The two stripes emitter ``name`` draws on screen ``name`` for the true pose ``T_M_O``.

    A fan parallel to the screen, or an emitter facing away from it, draws nothing.
    """
    screen = bench.screens[name]
    emitter = bench.emitters[name]
    beam = opr_in_m[:3, :3] @ emitter.beam
    if beam @ screen.normal <= 0.0:
        return []
    out = []
    for fan, (point, normal) in emitter.fan_planes_in_m(opr_in_m).items():
        a, b = normal @ screen.u, normal @ screen.v
        length = float(np.hypot(a, b))
        if length < 1e-9:
            continue
        c = normal @ (screen.origin - point)
        out.append(
            StripeOnScreen(
                fan, np.array([a, b]) / length, float(c / length), point, beam,
                emitter.fan_peak_levels[fan], emitter.stripe_sigma,
            )
        )
    return out


class Renderer:
    """Renders camera frames of a bench.

    Parameters
    ----------
    bench : OpticalBench
    seed : int
        Base seed; frame ``seq`` of camera ``name`` uses its own stream derived from it.
    bit_depth : 8 or 12
        Output depth: uint8 0–255 or uint16 0–4095.
    session : int
        The cell's session (``WorldConfig.session``): the noise is drawn anew in each; session 0 is
        the noise of a renderer that gives none.
    """

    def __init__(self, bench: OpticalBench, *, seed: int = 0, bit_depth: int = 8, session: int = 0) -> None:
        if bit_depth not in (8, 12):
            raise ValueError(f"bit_depth must be 8 or 12, got {bit_depth!r}")
        self.bench = bench
        self.seed = int(seed)
        self._session = [int(session)] if session else []  # appended to every noise seed of a later session
        self.bit_depth = bit_depth
        self.saturation = 255 if bit_depth == 8 else 4095
        self._background: dict[str, np.ndarray] = {}
        self._noise_pool: np.ndarray | None = None

    # ------------------------------------------------------------------ public
    def render(
        self,
        name: str,
        opr_in_m: np.ndarray,
        *,
        seq: int = 0,
        noise: bool = True,
        quantise: bool = True,
        exposure_scale: float = 1.0,
        roi: tuple[int, int, int, int] | None = None,
        blur: Sequence[np.ndarray] | None = None,
    ) -> np.ndarray:
        """One frame of camera ``name`` (``img[row, col]``).

        ``noise=False`` gives the ideal image (background and stripes, no speckle or noise);
        ``quantise=False`` returns float32 grey levels on the output scale, unclipped.
        ``roi`` = (offset_x, offset_y, width, height) renders only that window of the sensor.
        ``blur``: the OPR poses ``T_M_O`` at evenly spread instants of the exposure; each stripe is
        then the mean of its profiles at those poses (motion blur), laid out around its line at
        ``opr_in_m`` (the exposure's middle pose).
        """
        cfg = self.bench.config
        camera = self.bench.cameras[name]
        width, height = camera.size_px
        ox, oy, w, h = (0, 0, width, height) if roi is None else (int(v) for v in roi)
        if not (0 <= ox and 0 <= oy and w > 0 and h > 0 and ox + w <= width and oy + h <= height):
            raise ValueError(f"roi {roi} does not fit the {width} x {height} sensor")
        rng = np.random.default_rng([self.seed % 2**63, AXIS_NAMES.index(name), int(seq) % 2**63, *self._session])
        background = self._background_of(name)[oy:oy + h, ox:ox + w]
        if noise:
            sigma_bg = np.sqrt(cfg.read_noise**2 + cfg.conversion_gain * cfg.background_level)
            image = self._background_noise(rng, w, h) * np.float32(sigma_bg)
            image += background
        else:
            image = background.copy()
        speckle = self._speckle_field(rng, w, h) if noise and cfg.speckle_contrast > 0 else None
        sub_poses = [np.asarray(p, dtype=float) for p in blur] if blur else None
        for stripe in stripes_on_screen(self.bench, name, np.asarray(opr_in_m, dtype=float)):
            subs = None
            if sub_poses is not None:
                subs = [s for pose in sub_poses for s in stripes_on_screen(self.bench, name, pose)
                        if s.fan == stripe.fan]
                if len(subs) != len(sub_poses):
                    subs = None  # the fan left the screen during the exposure: no blur for this stripe
            band = self._stripe_band(name, stripe, subs)
            if band is None:
                continue
            rows, cols, signal = band
            if roi is not None:
                inside = (rows >= oy) & (rows < oy + h) & (cols >= ox) & (cols < ox + w)
                rows, cols, signal = rows[inside] - oy, cols[inside] - ox, signal[inside]
            signal *= exposure_scale
            if speckle is not None:
                grain = cfg.speckle_grain_px
                factor = map_coordinates(speckle, [rows / grain, cols / grain], order=1, mode="nearest")
                signal *= np.maximum(0.0, 1.0 + cfg.speckle_contrast * factor)
            if noise:
                signal += np.sqrt(cfg.conversion_gain * np.maximum(signal, 0.0)) * rng.standard_normal(signal.shape)
            image[rows, cols] += signal.astype(np.float32)
        scale = self.saturation / 255.0
        if scale != 1.0:
            image *= np.float32(scale)
        if not quantise:
            return image
        image += np.float32(0.5)  # round half up on the cast below
        np.clip(image, 0.0, self.saturation, out=image)
        return image.astype(np.uint8 if self.bit_depth == 8 else np.uint16)

    def render_all(self, opr_in_m: np.ndarray, *, seq: int = 0, names: Iterable[str] = AXIS_NAMES,
                   **kwargs) -> dict[str, np.ndarray]:
        return {name: self.render(name, opr_in_m, seq=seq, **kwargs) for name in names}

    # ------------------------------------------------------------------ pieces
    def _background_of(self, name: str) -> np.ndarray:
        if name not in self._background:
            cfg = self.bench.config
            width, height = self.bench.cameras[name].size_px
            # Separable: the squares per column and per row, summed by broadcasting (a full mgrid is
            # two 5 Mpx int64 arrays per camera at every cell start). Same float32 values.
            x = np.arange(width, dtype=np.float32)[None, :]
            y = np.arange(height, dtype=np.float32)[:, None]
            r2 = ((x - (width - 1) / 2) ** 2 + (y - (height - 1) / 2) ** 2) / (
                ((width - 1) / 2) ** 2 + ((height - 1) / 2) ** 2
            )
            self._background[name] = (cfg.background_level * (1.0 - cfg.vignetting * r2)).astype(np.float32)
        return self._background[name]

    def _background_noise(self, rng: np.random.Generator, width: int, height: int) -> np.ndarray:
        """Unit normal noise for the whole frame: a window at a random offset into a pool of iid
        normals drawn once. Drawing 5 M fresh normals per frame would cost ~75 ms; a window
        costs nothing, and two frames' windows only repeat values at a random pixel shift. The
        stripe band's noise (what the centre fits see) is drawn fresh for every frame."""
        size = width * height
        pool = self._noise_pool
        if pool is None or pool.size < size + _POOL_SLACK:
            pool = np.random.default_rng([self.seed % 2**63, 0x6E6F, *self._session]).standard_normal(
                size + _POOL_SLACK, dtype=np.float32
            )
            self._noise_pool = pool
        start = int(rng.integers(0, pool.size - size + 1))
        return pool[start:start + size].reshape(height, width)

    def _speckle_field(self, rng: np.random.Generator, width: int, height: int) -> np.ndarray:
        grain = self.bench.config.speckle_grain_px
        shape = (int(np.ceil(height / grain)) + 3, int(np.ceil(width / grain)) + 3)
        field = gaussian_filter(rng.standard_normal(shape, dtype=np.float32), 1.0, mode="wrap")
        return field / np.float32(1.0 / (2.0 * np.sqrt(np.pi)))  # unit variance (2-D Gaussian, σ = 1 cell)

    def _stripe_band(self, name: str, stripe: StripeOnScreen, blur: list[StripeOnScreen] | None = None):
        """Pixels within ±6σ of the stripe: (rows, cols, ideal signal in 8-bit grey levels). With
        ``blur`` (the same fan's stripe at several instants of the exposure) the band also covers
        where those lines run, and the profile is their mean."""
        bench = self.bench
        camera, screen = bench.cameras[name], bench.screens[name]
        width, height = camera.size_px
        polyline = self._visible_polyline(name, stripe)
        if polyline is None:
            return None
        xs, ys = polyline[:, 0], polyline[:, 1]
        along_x = np.ptp(xs) >= np.ptp(ys)
        # Walk the stripe along its long image direction: per column (near-horizontal stripe)
        # or per row (near-vertical), a short run of pixels across it.
        lead, cross = (xs, ys) if along_x else (ys, xs)
        order = np.argsort(lead)
        lead, cross = lead[order], cross[order]
        lead_size, cross_size = (width, height) if along_x else (height, width)
        steps = np.arange(max(0, int(np.ceil(lead[0]))), min(lead_size - 1, int(np.floor(lead[-1]))) + 1)
        if steps.size == 0:
            return None
        centre = np.interp(steps, lead, cross)
        centre_xy = np.stack([steps, centre], -1) if along_x else np.stack([centre, steps], -1)
        # Local metres-per-pixel of the distance function, per step (it varies slowly).
        h = 0.5
        d0 = stripe.distance(camera.pixel_to_screen(centre_xy))
        gx = (stripe.distance(camera.pixel_to_screen(centre_xy + [h, 0.0])) - d0) / h
        gy = (stripe.distance(camera.pixel_to_screen(centre_xy + [0.0, h])) - d0) / h
        grad = np.hypot(gx, gy)
        sigma_px = stripe.sigma / grad
        slope = np.abs(np.gradient(centre, steps)) if steps.size > 1 else np.zeros(1)
        spread = 0.0  # how far (px) the blurred lines run from this one
        if blur:
            uv_steps = camera.pixel_to_screen(centre_xy)
            spread = max(float(np.max(np.abs(sub.distance(uv_steps)) / grad)) for sub in blur)
        half = int(np.ceil((6.0 * sigma_px.max() + spread) * np.sqrt(1.0 + slope.max() ** 2))) + 2
        offsets = np.arange(-half, half + 1)
        across = np.rint(centre)[None, :].astype(int) + offsets[:, None]
        along = np.broadcast_to(steps[None, :], across.shape)
        inside = (across >= 0) & (across < cross_size)
        across, along = across[inside], along[inside]
        step_index = np.broadcast_to(np.arange(steps.size)[None, :], inside.shape)[inside]
        rows, cols = (across, along) if along_x else (along, across)
        pixels = np.stack([cols, rows], -1).astype(float)
        uv = camera.pixel_to_screen(pixels)
        s = sigma_px[step_index]
        g = grad[step_index]
        lines = blur or [stripe]
        profile = np.zeros(len(uv))
        for line in lines:
            d_px = line.distance(uv) / g
            profile += ndtr((d_px + 0.5) / s) - ndtr((d_px - 0.5) / s)
        profile *= _SQRT_2PI * s / len(lines)
        # Peak level per step: 1/r from the emitter, Gaussian fall-off along the fan.
        uv_centre = camera.pixel_to_screen(centre_xy)
        ray = screen.to_m(uv_centre) - stripe.emitter_point
        r = np.linalg.norm(ray, axis=-1)
        cos_psi = np.clip(ray @ stripe.beam / r, -1.0, 1.0)
        psi = np.arccos(cos_psi)
        level = (
            stripe.peak_level
            * (bench.config.screen_distance / r)
            * np.exp(-2.0 * (psi / bench.config.fan_half_angle) ** 2)
        )
        level = np.where(cos_psi > 0.0, level, 0.0)
        return rows, cols, profile * level[step_index]

    def _visible_polyline(self, name: str, stripe: StripeOnScreen, samples: int = 256):
        """The stripe's image as a polyline over the camera's view (plus margin), or None."""
        camera = self.bench.cameras[name]
        width, height = camera.size_px
        border = np.array([[-20, -20], [width + 19, -20], [width + 19, height + 19], [-20, height + 19]], float)
        corners_uv = camera.pixel_to_screen(border)
        point, direction = stripe.point_and_direction()
        # Project the view's corners onto the line to bound the stretch of it that can be seen.
        along = (corners_uv - point) @ direction
        across = (corners_uv - point) @ stripe.normal
        if across.min() > 0.0 or across.max() < 0.0:
            return None  # the line misses the view altogether
        s = np.linspace(along.min(), along.max(), samples)
        return camera.screen_to_pixel(point + s[:, None] * direction)


__all__ = ["FANS", "Renderer", "StripeOnScreen", "stripes_on_screen"]
