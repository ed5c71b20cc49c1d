"""Synthetic cross-line laser images with known truth, for the ``instrument.vision`` tests.

Written independently of ``instrument.vision`` (it only shares the conventions of method.md §2):
pixel (row r, col c) is the unit square centred at image point (x = c, y = r). A stripe is a
Gaussian line profile ``A·exp(-d²/2σ²)`` of the perpendicular distance ``d`` from its centre line,
integrated over each pixel's area: exactly (erf differences) across the stripe's main axis and by
a midpoint rule with ``SUBSAMPLES`` points along it.

Angles follow method.md §2.4: the horizontal stripe runs along ``(cos φh, sin φh)`` and the vertical
one along ``(-sin φv, cos φv)``; a rigid cross rotated by θ has φh = φv = θ.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import erf

SUBSAMPLES = 8  # midpoint-rule points per pixel along the stripe (the profile varies slowly there)


@dataclass(frozen=True)
class Truth:
    """What the image was made of."""

    center: np.ndarray  # (x, y) px
    phi_h: float
    phi_v: float

    @property
    def angle(self) -> float:
        return 0.5 * (self.phi_h + self.phi_v)

    @property
    def perpendicularity(self) -> float:
        return self.phi_v - self.phi_h


def gaussian_profile_pixels(offsets, sigma):
    """Unit-peak Gaussian integrated over pixels centred at ``offsets`` (px from the stripe centre).

    Returns the mean of ``exp(-d²/2σ²)`` over each pixel ``[o - 1/2, o + 1/2]`` (erf difference).
    """
    offsets = np.asarray(offsets, dtype=float)
    s = sigma * np.sqrt(2.0)
    return sigma * np.sqrt(np.pi / 2.0) * (erf((offsets + 0.5) / s) - erf((offsets - 0.5) / s))


def stripe_image(shape, point, phi, sigma, *, vertical=False, extent=None):
    """Unit-peak image of one straight stripe.

    Parameters
    ----------
    shape : (rows, cols)
    point : (x, y) a point on the stripe centre line
    phi : float
        Stripe angle per method.md §2.4 (φh for a horizontal stripe, φv for a vertical one).
    sigma : float
        Gaussian standard deviation across the stripe, px.
    vertical : bool
        False: the stripe is near-horizontal and integrated exactly over rows; True: near-vertical,
        integrated exactly over columns.
    extent : (float, float) or None
        Limits of the stripe along its own axis: x range for a horizontal stripe, y range for a
        vertical one (soft-free hard cut); None = the whole frame.
    """
    rows, cols = shape
    px, py = point
    if not vertical:
        # centre line y = py + tan(φh)·(x - px); integrate exactly over y in [r-1/2, r+1/2], only
        # within ±(8σ + margin) of the line (beyond, exp(-32) is far below any grey level)
        slope, cos_phi = np.tan(phi), np.cos(phi)
        sub = (np.arange(SUBSAMPLES) + 0.5) / SUBSAMPLES - 0.5
        x = np.arange(cols)[:, None] + sub[None, :]  # (cols, S)
        y_line = py + slope * (x - px)
        reach = int(np.ceil(8.0 * sigma / cos_phi + abs(slope) + 2))
        r = np.rint(y_line.mean(axis=1))[None, :] + np.arange(-reach, reach + 1)[:, None]  # (K, cols)
        lo = (r[:, :, None] - 0.5 - y_line[None]) * cos_phi  # perpendicular distances, (K, cols, S)
        hi = lo + cos_phi
        s = sigma * np.sqrt(2.0)
        val = sigma * np.sqrt(np.pi / 2.0) / cos_phi * (erf(hi / s) - erf(lo / s))
        if extent is not None:
            val = val * ((x >= extent[0]) & (x <= extent[1]))[None]
        out = np.zeros(shape)
        inside = (r >= 0) & (r < rows)
        col_index = np.broadcast_to(np.arange(cols)[None, :], r.shape)
        out[r[inside].astype(int), col_index[inside]] = val.mean(axis=2)[inside]
        return out
    # vertical: centre line x = px - tan(φv)·(y - py)
    return stripe_image((cols, rows), (py, px), -phi, sigma, vertical=False, extent=extent).T


def render_cross(
    shape=(240, 320),
    center=(160.0, 120.0),
    angle=0.0,
    perpendicularity=0.0,
    *,
    sigma=2.0,
    amplitude=200.0,
    background=10.0,
    noise=2.0,
    saturation=255,
    dtype=np.uint8,
    seed=0,
    h_extent=None,
    v_extent=None,
    horizontal=True,
    vertical=True,
    extra_crosses=(),
    vertical_amplitude=None,
    background_gradient=(0.0, 0.0),
):
    """A cross image with known truth.

    Parameters
    ----------
    shape : (rows, cols)
    center : (x, y) px, intersection of the two stripe centre lines
    angle, perpendicularity : float, rad
        θ and φv − φh; φh = θ − p/2 and φv = θ + p/2.
    sigma, amplitude, background, noise : float
        Stripe σ (px), peak above background, background level and Gaussian noise σn (grey levels).
    saturation : int
        Clip level; the sensor's full scale (255, 4095, 65535).
    dtype : numpy dtype, uint8 or uint16
    seed : int, noise seed
    h_extent, v_extent : (lo, hi) or None
        Limit a stripe to x in [lo, hi] (horizontal) or y in [lo, hi] (vertical).
    horizontal, vertical : bool
        Leave out one of the stripes.
    extra_crosses : sequence of (center, angle)
        Further crosses of the same kind (to test the "two crosses" error).
    vertical_amplitude : float or None
        Peak of the vertical stripe if it differs from ``amplitude`` (two unequal fan lasers).
    background_gradient : (gx, gy)
        Ambient light slope in grey levels per pixel along x and y, about the frame's centre.

    Returns
    -------
    img : ndarray of ``dtype``
    truth : Truth
    """
    phi_h = angle - perpendicularity / 2.0
    phi_v = angle + perpendicularity / 2.0
    light = np.zeros(shape)
    if horizontal:
        light += amplitude * stripe_image(shape, center, phi_h, sigma, extent=h_extent)
    if vertical:
        v_amp = amplitude if vertical_amplitude is None else vertical_amplitude
        light += v_amp * stripe_image(shape, center, phi_v, sigma, vertical=True, extent=v_extent)
    for c, a in extra_crosses:
        light += amplitude * stripe_image(shape, c, a, sigma)
        light += amplitude * stripe_image(shape, c, a, sigma, vertical=True)
    rows, cols = shape
    ambient = background + background_gradient[0] * (np.arange(cols)[None, :] - (cols - 1) / 2.0)
    ambient = ambient + background_gradient[1] * (np.arange(rows)[:, None] - (rows - 1) / 2.0)
    rng = np.random.default_rng(seed)
    img = ambient + light + rng.normal(0.0, noise, size=shape)
    img = np.clip(np.rint(img), 0, saturation).astype(dtype)
    return img, Truth(np.array(center, dtype=float), phi_h, phi_v)


def section_profiles(n, *, sigma=2.0, amplitude=200.0, background=10.0, noise=2.0, saturation=255,
                     length=25, seed=0, quantize=True):
    """Monte-Carlo cross-sections: ``n`` noisy integrated Gaussian profiles at random sub-pixel centres.

    Returns
    -------
    profiles : (length, n) float array of grey levels, clipped at ``saturation`` and (unless
        ``quantize`` is False) rounded to integers like a sensor
    centers : (n,) true centres in pixel index units along the profile
    """
    rng = np.random.default_rng(seed)
    centers = (length - 1) / 2.0 + rng.uniform(-0.5, 0.5, size=n)
    idx = np.arange(length)[:, None]
    clean = background + amplitude * gaussian_profile_pixels(idx - centers[None, :], sigma)
    noisy = clean + rng.normal(0.0, noise, size=clean.shape)
    if quantize:
        noisy = np.rint(noisy)
    return np.clip(noisy, 0, saturation), centers


def cramer_rao(sigma, amplitude, noise):
    """Cramér–Rao bound on one section's centre, px (method.md §2): σn/A·sqrt(2σ/√π)."""
    return noise / amplitude * np.sqrt(2.0 * sigma / np.sqrt(np.pi))
