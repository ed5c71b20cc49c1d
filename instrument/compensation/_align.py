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

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from instrument.compensation._data import point_means
from instrument.compensation._spline import fit_spline_curve


class Curve(Protocol):
    def predict(self, x: np.ndarray) -> np.ndarray: ...


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
    offsets: dict[int, float]
    interval: tuple[float, float] | None

    def offset(self, group: int) -> float:
        return float(self.offsets.get(int(group), 0.0))

    def apply(self, error: np.ndarray, group: np.ndarray) -> np.ndarray:
        """Error brought into the reference group's frame (unknown groups get no offset)."""
        return error + self.offsets_of(group)

    def offsets_of(self, group: np.ndarray) -> np.ndarray:
        """The offset of each observation's group (0 for a group the alignment does not know)."""
        group = np.asarray(group)
        out = np.zeros(group.shape)
        for g, value in self.offsets.items():
            out[group == g] = value
        return out

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
    def identity(cls, groups: Iterable[int] | np.ndarray = (0,)) -> GroupAlignment:
        groups = sorted({int(g) for g in groups})
        return cls(groups[0], dict.fromkeys(groups, 0.0), None)


def stable_interval(curve: Curve, x_points: np.ndarray, window_points: int) -> tuple[float, float]:
    """Window of consecutive calibration points where the curve varies least.

    Parameters
    ----------
    curve : anything with ``predict(x)``
    x_points : calibration point positions
    window_points : points per window (at least 2)

    Returns
    -------
    (lo, hi) : the window with the least total variation ∫|g'| of the curve
    """
    x_points = np.sort(np.asarray(x_points, dtype=float))
    window_points = int(min(max(window_points, 2), x_points.size))
    per_step = 40  # samples per calibration step: enough to see a ripple's turning points
    fine = np.concatenate([np.linspace(a, b, per_step, endpoint=False) for a, b in zip(x_points[:-1], x_points[1:])]
                          + [x_points[-1:]])
    variation = np.abs(np.diff(np.asarray(curve.predict(fine), dtype=float)))
    per_interval = variation.reshape(x_points.size - 1, per_step).sum(axis=1)
    steps = window_points - 1
    totals = np.convolve(per_interval, np.ones(steps), mode="valid")
    start = int(np.argmin(totals))
    return float(x_points[start]), float(x_points[start + steps])


def _offsets_against(curve: Curve, x: np.ndarray, e: np.ndarray, group: np.ndarray, point: np.ndarray,
                     interval_points: np.ndarray, groups: list[int]) -> dict[int, float]:
    """Mean of (curve − group point means) over the interval's calibration points, per group.

    The interval is a set of point labels, the same for every group, so whatever the curve misses
    at those points (a ripple it smooths away) is missed equally in every group and cancels in
    the offsets relative to the reference group. Choosing the points by measured value instead
    let a group whose offset moved an end point across the interval's edge average over other
    points (a 4 µm misfit at one end point biased the offsets by 0.8 µm).
    """
    offsets = {}
    for g in groups:
        sel = group == g
        xm, em, _, labels = point_means(x[sel], e[sel], point[sel])
        inside = np.isin(labels, interval_points)
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
    measured, error, group, point : (n,) observation arrays (error = measured − reference, derived
        by the caller: ``aligned_points(data)`` is the entry point that takes CalibrationData)
    window_fraction : fraction of the calibration points spanned by the stable interval
    refine : re-estimate the offsets once against the pooled curve of the aligned data

    Returns
    -------
    GroupAlignment
    """
    x, e = np.asarray(measured, float), np.asarray(error, float)
    group, point = np.asarray(group, int), np.asarray(point, int)
    groups = sorted(set(group.tolist()))
    if len(groups) == 1:
        return GroupAlignment.identity(groups)
    reference = groups[0]
    sel = group == reference
    xm, em, wm, labels = point_means(x[sel], e[sel], point[sel])
    reference_curve = fit_spline_curve(xm, em, wm)  # step 2: the reference group's CSF
    window = int(np.ceil(window_fraction * xm.size))
    interval = stable_interval(reference_curve, xm, max(window, 3))
    interval_points = labels[(xm >= interval[0]) & (xm <= interval[1])]
    offsets = _offsets_against(reference_curve, x, e, group, point, interval_points, groups)
    offsets[reference] = 0.0
    if refine:
        aligned = e + np.array([offsets[g] for g in group])
        xp, ep, wp, _ = point_means(x, aligned, point)
        pooled = fit_spline_curve(xp, ep, wp)
        pooled_offsets = _offsets_against(pooled, x, e, group, point, interval_points, groups)
        offsets = {g: pooled_offsets[g] - pooled_offsets[reference] for g in groups}
    return GroupAlignment(reference, offsets, interval)
