"""Group alignment (paper §3.4 step 3, eqs 33–37).

Each calibration group starts from a different initial pose, so its error curve sits at its own
offset. Fit a CSF curve per group (step 2), pick the interval of calibration points where the
reference group's curve varies least ("stable trend"), and shift every other group by the mean
of (reference curve − group error) over that interval. The paper's per-point coefficients
a_i (eq 33) are averaged over the interval into one offset per group: adding a_i point by point
(eq 36 taken literally) would copy the reference curve and erase the other groups' information.

One refinement pass re-estimates all offsets against the pooled curve of the aligned data, so
the reference group's own noise is averaged down; offsets stay relative to the reference group.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from instrument.compensation._data import point_means
from instrument.compensation._spline import fit_spline_curve


@dataclass(frozen=True)
class GroupAlignment:
    """Offsets added to each group's error to bring it onto the reference group's curve.

    Attributes
    ----------
    reference_group : int
    offsets : dict group → offset (same unit as the error); the reference group's is 0
    interval : (lo, hi) measured-value interval used for the offsets, or None (single group)
    """

    reference_group: int
    offsets: dict
    interval: tuple | None

    def offset(self, group: int) -> float:
        return float(self.offsets.get(int(group), 0.0))

    def apply(self, error: np.ndarray, group: np.ndarray) -> np.ndarray:
        return error + np.array([self.offset(g) for g in group])

    def to_dict(self) -> dict:
        return {
            "reference_group": int(self.reference_group),
            "offsets": {str(k): float(v) for k, v in self.offsets.items()},
            "interval": None if self.interval is None else [float(v) for v in self.interval],
        }

    @classmethod
    def from_dict(cls, d: dict) -> GroupAlignment:
        interval = d["interval"]
        return cls(
            int(d["reference_group"]),
            {int(k): float(v) for k, v in d["offsets"].items()},
            None if interval is None else (float(interval[0]), float(interval[1])),
        )

    @classmethod
    def identity(cls, groups=(0,)) -> GroupAlignment:
        groups = sorted({int(g) for g in groups})
        return cls(groups[0], dict.fromkeys(groups, 0.0), None)


def stable_interval(curve, x_points: np.ndarray, window_points: int) -> tuple[float, float]:
    """Window of ``window_points`` consecutive calibration points with the least total variation
    ∫|g'| of the curve (the error curve varies least there)."""
    x_points = np.sort(np.asarray(x_points, dtype=float))
    window_points = int(min(max(window_points, 2), x_points.size))
    best, best_tv = (x_points[0], x_points[window_points - 1]), np.inf
    for start in range(x_points.size - window_points + 1):
        lo, hi = x_points[start], x_points[start + window_points - 1]
        fine = curve.predict(np.linspace(lo, hi, 40 * window_points))
        tv = np.sum(np.abs(np.diff(fine)))
        if tv < best_tv:
            best, best_tv = (float(lo), float(hi)), tv
    return best


def _offsets_against(curve, x, e, group, point, interval, groups):
    offsets = {}
    for g in groups:
        sel = group == g
        xm, em, _, _ = point_means(x[sel], e[sel], point[sel])
        inside = (xm >= interval[0]) & (xm <= interval[1])
        if not np.any(inside):  # the group never visits the interval: use all its points
            inside = np.ones_like(xm, dtype=bool)
        offsets[int(g)] = float(np.mean(curve.predict(xm[inside]) - em[inside]))
    return offsets


def align_groups(
    measured: np.ndarray,
    error: np.ndarray,
    group: np.ndarray,
    point: np.ndarray,
    *,
    window_fraction: float = 1.0 / 3.0,
    refine: bool = True,
) -> GroupAlignment:
    """Estimate one offset per calibration group (paper §3.4 step 3).

    Parameters
    ----------
    measured, error, group, point : (n,) observation arrays
    window_fraction : fraction of the calibration points spanned by the stable interval
    refine : re-estimate the offsets once against the pooled curve of the aligned data
    """
    x, e = np.asarray(measured, float), np.asarray(error, float)
    group, point = np.asarray(group, int), np.asarray(point, int)
    groups = sorted(set(group.tolist()))
    if len(groups) == 1:
        return GroupAlignment.identity(groups)
    reference = groups[0]
    sel = group == reference
    xm, em, wm, _ = point_means(x[sel], e[sel], point[sel])
    reference_curve = fit_spline_curve(xm, em, wm)  # step 2: the reference group's CSF
    window = int(np.ceil(window_fraction * xm.size))
    interval = stable_interval(reference_curve, xm, max(window, 3))
    offsets = _offsets_against(reference_curve, x, e, group, point, interval, groups)
    offsets[reference] = 0.0
    if refine:
        aligned = e + np.array([offsets[g] for g in group])
        xp, ep, wp, _ = point_means(x, aligned, point)
        pooled = fit_spline_curve(xp, ep, wp)
        pooled_offsets = _offsets_against(pooled, x, e, group, point, interval, groups)
        offsets = {g: pooled_offsets[g] - pooled_offsets[reference] for g in groups}
    return GroupAlignment(reference, offsets, interval)
