"""Input checking and the angle branch rule shared by the characteristics."""

from __future__ import annotations

import numpy as np

from instrument.iso9283._errors import ISO9283Error


def wrap_angle(angle):
    """Wrap into (−π, π]."""
    wrapped = np.mod(np.asarray(angle, dtype=float) + np.pi, 2.0 * np.pi) - np.pi
    return np.where(wrapped == -np.pi, np.pi, wrapped)


def circular_mean(angles: np.ndarray, name: str = "angles") -> float:
    """Mean direction atan2(Σ sin, Σ cos); refuses a set spread around the whole circle."""
    s, c = np.sin(angles).mean(), np.cos(angles).mean()
    if np.hypot(s, c) < 1e-3:
        raise ISO9283Error(f"{name}: the angles are spread around the whole circle; their mean is undefined")
    return float(np.arctan2(s, c))


def unwrap_about_mean(angles: np.ndarray, name: str = "angles") -> np.ndarray:
    """Bring angles onto one branch around their circular mean (values near ±π stay together)."""
    mean = circular_mean(angles, name)
    return mean + wrap_angle(angles - mean)


def as_poses(poses, name: str = "poses", minimum: int = 2) -> np.ndarray:
    """Validate an (n, 6) array [x, y, z, a, b, c] (m, rad) and unwrap its angle columns."""
    try:
        array = np.array(poses, dtype=float)
    except (TypeError, ValueError):
        raise ISO9283Error(f"{name}: expected an (n, 6) array [x, y, z, a, b, c] of numbers") from None
    if array.ndim != 2 or array.shape[1] != 6:
        raise ISO9283Error(f"{name}: expected an (n, 6) array [x, y, z, a, b, c] (m, rad), got shape {array.shape}")
    if len(array) < minimum:
        raise ISO9283Error(f"{name}: needs at least {minimum} attained poses, got {len(array)}")
    bad = ~np.isfinite(array)
    if bad.any():
        row, column = np.argwhere(bad)[0]
        raise ISO9283Error(f"{name}: non-finite value at pose {row}, column {'xyzabc'[column]!r}")
    # unwrap_about_mean on the three angle columns at once (one set of NumPy calls instead of three:
    # the Monte Carlo of a run's uncertainty validates a pose set tens of thousands of times). Each
    # row of the transposed copy is contiguous, so its means are summed as a column's alone would be.
    angles = np.ascontiguousarray(array[:, 3:].T)
    s, c = np.sin(angles).mean(axis=1), np.cos(angles).mean(axis=1)
    spread = np.hypot(s, c) < 1e-3
    if spread.any():
        column = 3 + int(np.argmax(spread))
        raise ISO9283Error(f"{name}[:, {'xyzabc'[column]!r}]: the angles are spread around the whole circle; "
                           "their mean is undefined")
    mean = np.arctan2(s, c)[:, None]
    array[:, 3:] = (mean + wrap_angle(angles - mean)).T
    return array


def as_commanded(commanded, name: str = "commanded") -> np.ndarray:
    try:
        array = np.asarray(commanded, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ISO9283Error(f"{name}: expected [x, y, z, a, b, c] (m, rad)") from None
    if array.shape != (6,):
        raise ISO9283Error(f"{name}: expected [x, y, z, a, b, c] (m, rad), got shape {np.shape(commanded)}")
    if not np.all(np.isfinite(array)):
        raise ISO9283Error(f"{name}: must be finite, got {array.tolist()}")
    return array
