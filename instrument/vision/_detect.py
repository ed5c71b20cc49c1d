"""Finding the two stripes of a cross cheaply (method.md §2.1).

Works on a block-averaged copy of the frame (about 256 px on its long side; a power-of-two
factor), so the full-resolution image is read once by the averaging and never converted to float:

1. background = median, noise = scaled MAD of the small image; no cross if nothing stands out;
2. binarise at a set level above background (a fraction of the contrast, never below 6 noise σ),
   or Otsu's level on request;
3. Hough transform (1° steps) of the binary image, itself reduced 2× more; the strongest
   near-horizontal and the strongest near-vertical line are the two stripes (split at 45°);
4. each line is refined on the small image (intensity centroids per small column/row, trimmed fit,
   the crossing left out) to about a pixel of the full frame;
5. what the two stripes do not explain is searched again for lines: another long stripe means two
   crosses (or a stray stripe), which is an error, not a guess.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from instrument.vision._linefit import _median, _weighted_line
from instrument.vision._types import CrossNotFound

SMALL_SIDE = 256  # target long side of the block-averaged image, px
HOUGH_THETA = np.pi / 180.0
MIN_CONTRAST_SIGMAS = 10.0  # the brightest structure must stand this many noise σ above background
LEVEL_FRACTION = 0.15  # binarisation level as a fraction of the contrast (dim stripes down to ~1/5)
MIN_STRIPE_PX = 40.0  # a stripe shorter than this (full-resolution px) is not looked for
EXTRA_STRIPE_FRACTION = 0.3  # another line with this share of the weaker stripe's votes = 2nd cross
HOUGH_MIN_SIDE = 96  # Hough on a 2× further reduced copy only if that keeps ≥ this many px a side
REFINE_MIN_RADIUS = 5  # small-image px searched either side of the Hough line


@dataclass(frozen=True)
class CoarseLine:
    """A stripe centre line in full-resolution pixels: ``dependent = intercept + slope·independent``.

    For a horizontal stripe the independent coordinate is x (y = a + b·x); for a vertical one it is
    y (x = a + b·y).
    """

    vertical: bool
    intercept: float
    slope: float
    votes: int

    def at(self, independent):
        """Dependent coordinate of the line at ``independent`` (array_like)."""
        return self.intercept + self.slope * np.asarray(independent, dtype=float)

    def describe(self) -> str:
        """E.g. ``near-vertical stripe (x ≈ 113 − 0.052·y)``, full-resolution pixels."""
        kind = "near-vertical" if self.vertical else "near-horizontal"
        dep, ind = ("x", "y") if self.vertical else ("y", "x")
        sign = "+" if self.slope >= 0 else "−"
        return f"{kind} stripe ({dep} ≈ {self.intercept:.0f} {sign} {abs(self.slope):.3f}·{ind})"


@dataclass(frozen=True)
class Detection:
    """The two coarse stripes and the frame statistics found on the way."""

    horizontal: CoarseLine
    vertical: CoarseLine
    background: float
    small_noise: float
    factor: int


def block_factor(shape) -> int:
    """Power-of-two averaging factor bringing the long side of ``shape`` near ``SMALL_SIDE``."""
    return int(2 ** max(0, int(np.floor(np.log2(max(shape) / SMALL_SIDE)))))


def downsample(img, factor):
    """Block means of ``factor``×``factor`` pixels (the frame cropped to whole blocks).

    For factors ≥ 4 only every second row is read: that halves the memory traffic, the dominant
    cost, and still samples any stripe with σ ≥ 1 px within 1 px of its centre.
    """
    if factor == 1:
        return img
    rows, cols = (img.shape[0] // factor) * factor, (img.shape[1] // factor) * factor
    source = img[:rows:2, :cols] if factor >= 4 else img[:rows, :cols]
    return cv2.resize(source, (cols // factor, rows // factor), interpolation=cv2.INTER_AREA)


def _otsu_level(small, saturation):
    if small.dtype == np.uint8:
        scaled = small
    else:
        scaled = np.clip(small * (255.0 / saturation), 0, 255).astype(np.uint8)
    level, _ = cv2.threshold(scaled, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return level if small.dtype == np.uint8 else level * saturation / 255.0


def _hough(binary, min_votes):
    lines = cv2.HoughLinesWithAccumulator(binary, 1, HOUGH_THETA, int(min_votes))
    return np.empty((0, 3)) if lines is None else lines.reshape(-1, 3)


def _classify(lines):
    """Split Hough lines (rho, theta, votes) into near-horizontal and near-vertical ones."""
    theta = lines[:, 1]
    horizontal = (theta >= np.pi / 4) & (theta < 3 * np.pi / 4)
    return lines[horizontal], lines[~horizontal]


def _small_line(rho, theta, votes, vertical):
    """Hough (rho, theta) → CoarseLine in small-image pixel coordinates."""
    c, s = np.cos(theta), np.sin(theta)
    if vertical:  # x·c + y·s = rho → x = rho/c − (s/c)·y
        return CoarseLine(True, rho / c, -s / c, int(votes))
    return CoarseLine(False, rho / s, -c / s, int(votes))


def _to_full(line, factor):
    """Small-image line → full-resolution line (block k spans pixels k·f … k·f+f−1)."""
    shift = (factor - 1) / 2.0
    return CoarseLine(
        line.vertical, factor * line.intercept + shift - line.slope * shift, line.slope, line.votes
    )


def _to_coarse(line, factor):
    """Inverse of :func:`_to_full`."""
    shift = (factor - 1) / 2.0
    slope = line.slope
    return CoarseLine(line.vertical, (line.intercept - shift + slope * shift) / factor, slope, line.votes)


def _refine(small, line, other, level, background, radius):
    """Intensity centroids across ``line`` in each small column/row, then a trimmed line fit."""
    height, width = small.shape
    n_sections, across_len = (height, width) if line.vertical else (width, height)
    x = np.arange(n_sections)
    position = line.at(x)
    t = np.arange(-radius, radius + 1)
    r = np.rint(position).astype(np.intp)[None, :] + t[:, None]  # (2·radius+1, sections)
    inside = (r >= 0) & (r < across_len)
    rc = np.clip(r, 0, across_len - 1)
    index = x[None, :] * width + rc if line.vertical else rc * width + x[None, :]
    values = small.ravel().take(index).astype(np.float32)
    excess = values - np.float32(background)
    excess[~inside | (values <= level)] = 0.0
    total = excess.sum(axis=0)
    # leave out the crossing: sections the other stripe passes through within the band
    other_x = other.at(position)  # the other line's coordinate along this one's independent axis
    keep = (total > 0) & (np.abs(x - other_x) > radius * (1.0 + abs(other.slope)) + radius)
    if keep.sum() < 3:
        return line
    centroid = (excess * r).sum(axis=0)[keep] / total[keep]
    intercept, slope = _trimmed_line(x[keep].astype(float), centroid.astype(float))
    return CoarseLine(line.vertical, intercept, slope, line.votes)


def _trimmed_line(u, v):
    """Least-squares line v = a + b·u, refitted once without points beyond 3 RMS (+0.5 px).

    A pixel-level answer is all the refinement needs; two plain fits are cheaper than IRLS.
    """
    u0 = u.mean()
    du = u - u0
    weight = np.ones_like(du)
    intercept, slope = _weighted_line(du, v, weight)
    residual = v - (intercept + slope * du)
    inlier = np.abs(residual) <= 3.0 * np.sqrt(np.mean(residual * residual)) + 0.5
    if inlier.sum() >= 3 and not inlier.all():
        intercept, slope = _weighted_line(du, v, inlier.astype(float))
    return float(intercept - slope * u0), float(slope)


def _erase(binary, line, half_width):
    """Black out a band of ``half_width`` px around ``line`` in ``binary`` (in place)."""
    rows, cols = binary.shape
    span = np.array([-1.0, cols if not line.vertical else rows]) * 2.0
    dep = line.at(span)
    ends = np.column_stack([dep, span] if line.vertical else [span, dep])
    p1, p2 = (tuple(int(round(v)) for v in end) for end in ends)
    cv2.line(binary, p1, p2, 0, thickness=2 * half_width + 1)


def find_stripes(img, saturation, threshold=None) -> Detection:
    """Locate the two stripes of the cross to about a pixel (see the module docstring).

    Parameters
    ----------
    img : 2-D uint8/uint16 ndarray
    saturation : float
        Full-scale level of the sensor.
    threshold : None, float or "otsu"
        Binarisation level in grey levels; None = automatic set level; "otsu" = Otsu's method.

    Raises
    ------
    CrossNotFound
        No cross, only one stripe, or more than one cross.
    """
    factor = block_factor(img.shape)
    small = downsample(img, factor)
    # ~1000 blocks spread over the frame: the stripes cover a few per cent of them
    sample = small[:: max(1, small.shape[0] // 32), :: max(1, small.shape[1] // 32)].ravel().astype(float)
    background = _median(sample)
    small_noise = max(1.4826 * _median(np.abs(sample - background)), 0.5)
    contrast = float(small.max()) - background
    if contrast < MIN_CONTRAST_SIGMAS * small_noise:
        raise CrossNotFound(
            f"no cross in the image: nothing stands out of the background (brightest block "
            f"{contrast:.1f} grey levels above background {background:.1f}, noise {small_noise:.1f})"
        )
    if threshold is None:
        level = background + max(LEVEL_FRACTION * contrast, 6.0 * small_noise)
    elif isinstance(threshold, str):
        if threshold != "otsu":
            raise ValueError(f"threshold must be None, a grey level or 'otsu', got {threshold!r}")
        level = _otsu_level(small, saturation)
    else:
        level = float(threshold)

    # the Hough transform runs on a further 2× reduced copy (its cost grows with the pixel count);
    # the refinement then works on ``small`` again
    hough_scale = 2 if min(small.shape) >= 2 * HOUGH_MIN_SIDE else 1
    coarse = downsample(small, hough_scale) if hough_scale > 1 else small
    if threshold is None:
        coarse_contrast = float(coarse.max()) - background
        coarse_level = background + max(LEVEL_FRACTION * coarse_contrast, 6.0 * small_noise / hough_scale)
    else:
        coarse_level = level
    binary = (coarse > coarse_level).astype(np.uint8)
    min_votes = max(8, int(MIN_STRIPE_PX / (factor * hough_scale)))
    lines = _hough(binary, min_votes)
    horizontal, vertical = _classify(lines)
    if len(horizontal) == 0 and len(vertical) == 0:
        raise CrossNotFound(
            f"no cross in the image: bright pixels above level {coarse_level:.1f} form no stripe "
            f"(at least {MIN_STRIPE_PX:.0f} px long)"
        )
    if len(horizontal) == 0 or len(vertical) == 0:
        found = "near-vertical" if len(horizontal) == 0 else "near-horizontal"
        missing = "near-horizontal" if len(horizontal) == 0 else "near-vertical"
        raise CrossNotFound(
            f"only one stripe found ({found}); no {missing} stripe of at least {MIN_STRIPE_PX:.0f} px"
        )
    (h_rho, h_theta, h_votes), (v_rho, v_theta, v_votes) = horizontal[0], vertical[0]
    h = _to_full(_small_line(h_rho, h_theta, h_votes, vertical=False), hough_scale)
    v = _to_full(_small_line(v_rho, v_theta, v_votes, vertical=True), hough_scale)
    radius = max(REFINE_MIN_RADIUS, int(np.ceil(16.0 / factor)) + 1)
    h, v = _refine(small, h, v, level, background, radius), _refine(small, v, h, level, background, radius)

    # anything long and straight that the two stripes do not explain → more than one cross
    rest = binary.copy()
    erase = int(np.ceil(radius / hough_scale)) + 1
    _erase(rest, _to_coarse(h, hough_scale), erase)
    _erase(rest, _to_coarse(v, hough_scale), erase)
    if cv2.countNonZero(rest) >= min_votes:
        extra = _hough(rest, max(min_votes, EXTRA_STRIPE_FRACTION * min(h.votes, v.votes)))
        if len(extra):
            rho, theta, votes = extra[0]
            is_vertical = not (np.pi / 4 <= theta < 3 * np.pi / 4)
            stray = _to_full(_small_line(rho, theta, votes, is_vertical), factor * hough_scale)
            raise CrossNotFound(
                f"more than one cross in the image: besides the cross's two stripes there is "
                f"another {stray.describe()}"
            )
    return Detection(_to_full(h, factor), _to_full(v, factor), background, small_noise, factor)
