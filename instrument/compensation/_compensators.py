"""Compensators: one interface, the paper's CSF-PPSO-ESN and the baselines.

``Compensator.fit(data: CalibrationData) -> FittedModel`` runs the paper's four steps (§3.4) for
every method except ``none``:

1. the observations arrive as ``CalibrationData`` (measured + reference; the error is derived);
2. a CSF (smoothing spline) curve is fitted per group;
3. groups are aligned onto the first group's curve by one offset each, estimated in the interval
   where that curve varies least (``GroupAlignment``);
4. repeats are averaged at each calibration point and the method's curve is fitted to the
   aligned point means.

Approach direction. When the data holds both directions, step 4 takes, per point, the mid-way
value of the two directions' means for the method's curve, and half their difference for a
hysteresis curve (smoothing spline, λ by GCV, the same for every method): predicted error =
curve(x) + d·hysteresis(x). The offsets of step 3 are estimated on the error with the current
hysteresis estimate removed (twice: first without, then with it). A one-directional calibration
fits the curve of that direction and records which one it was.

``FittedModel.predict(measured, direction)`` is the predicted error in the reference group's
frame; the corrected value is ``measured − predict(measured, direction)``.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from instrument.compensation._align import GroupAlignment, align_groups
from instrument.compensation._baselines import (
    GaussianProcessCurve,
    PolynomialCurve,
    ZeroCurve,
    fit_gaussian_process,
    fit_polynomial,
)
from instrument.compensation._csf_esn import SELECTIONS, tune_csf_esn
from instrument.compensation._data import CalibrationData, check_direction, data_noise_floor, point_means
from instrument.compensation._esn import CsfEsnCurve
from instrument.compensation._legacy import LegacyEsnCurve, LegacySumCurve
from instrument.compensation._memo import Memo, digest
from instrument.compensation._ripple import MAX_RIPPLES, fit_ripple_spline
from instrument.compensation._spline import SplineCurve, fit_spline_curve

MIN_POINTS = 4


class Curve(Protocol):
    """An error curve: ``predict(measured) -> error`` and a JSON-able description (with its "kind")."""

    def predict(self, x: np.ndarray) -> np.ndarray: ...

    def to_dict(self) -> dict: ...


def curve_from_dict(d: dict) -> Curve:
    """Rebuild a curve from its ``to_dict()`` description.

    Raises
    ------
    ValueError
        Unknown kind or missing fields.
    """
    loaders: dict[str, Callable[[dict], Any]] = {
        ZeroCurve.kind: ZeroCurve.from_dict,
        SplineCurve.kind: SplineCurve.from_dict,
        PolynomialCurve.kind: PolynomialCurve.from_dict,
        GaussianProcessCurve.kind: GaussianProcessCurve.from_dict,
        CsfEsnCurve.kind: CsfEsnCurve.from_dict,
        LegacyEsnCurve.kind: LegacyEsnCurve.from_dict,
        LegacySumCurve.kind: LegacySumCurve.loader(curve_from_dict),
    }
    try:
        curve: Curve = loaders[d["kind"]](d)
    except KeyError as exc:
        raise ValueError(f"unknown or incomplete curve description: missing {exc}") from None
    return curve


@dataclass(frozen=True)
class FittedModel:
    """A fitted error model of one component.

    Attributes
    ----------
    method : name of the compensator that made it
    curve : error against measured value (mid-way between the approach directions when the
        calibration had both; else the error of the direction it had)
    alignment : group offsets found in step 3 (relative to the reference group)
    validity : (lo, hi) range of the measured values it was fitted on
    directions : approach directions the calibration covered: ``()`` not recorded, ``(1,)``,
        ``(-1,)`` or ``(-1, 1)``
    hysteresis : half the difference error(+1) − error(−1), or None (not bidirectional)
    details : JSON-able facts about the fit (chosen hyper-parameters, Pareto front, timings)
    """

    method: str
    curve: Curve
    alignment: GroupAlignment
    validity: tuple[float, float]
    directions: tuple[int, ...] = ()
    hysteresis: Curve | None = None
    details: dict = field(default_factory=dict)

    def predict(self, measured: np.ndarray | float, direction: np.ndarray | int | None = None) -> np.ndarray:
        """Predicted error at ``measured`` (same unit); corrected value = measured − this.

        Parameters
        ----------
        measured : array or float
        direction : None (mid-way), +1/−1, or an array of them; it matters only for a
            bidirectional model (a one-directional model knows one direction's error)
        """
        x = np.asarray(measured, dtype=float)
        error = np.asarray(self.curve.predict(x), dtype=float)
        d = check_direction(direction, "FittedModel.predict")
        if d is not None and self.hysteresis is not None:
            error = error + np.broadcast_to(d, x.shape) * np.asarray(self.hysteresis.predict(x), dtype=float)
        return error

    def group_offset(self, group: int) -> float:
        return self.alignment.offset(group)

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "curve": self.curve.to_dict(),
            "alignment": self.alignment.to_dict(),
            "validity": [float(self.validity[0]), float(self.validity[1])],
            "directions": [int(d) for d in self.directions],
            "hysteresis": None if self.hysteresis is None else self.hysteresis.to_dict(),
            "details": self.details,
        }

    @classmethod
    def from_dict(cls, d: dict) -> FittedModel:
        hysteresis = d.get("hysteresis")
        directions = tuple(int(v) for v in d.get("directions", ()))
        if any(v not in (-1, 1) for v in directions):
            raise ValueError(f"approach directions must be ±1, got {directions}")
        return cls(str(d["method"]), curve_from_dict(d["curve"]), GroupAlignment.from_dict(d["alignment"]),
                   (float(d["validity"][0]), float(d["validity"][1])), directions,
                   None if hysteresis is None else curve_from_dict(hysteresis), dict(d.get("details", {})))


@dataclass(frozen=True)
class AlignedPoints:
    """Step 3 and the averaging of step 4: what every method's curve is fitted to."""

    x: np.ndarray
    error: np.ndarray
    weight: np.ndarray
    alignment: GroupAlignment
    hysteresis: SplineCurve | PolynomialCurve | None
    noise_sigma: float | None


def _half_differences(x: np.ndarray, error: np.ndarray, group: np.ndarray, point: np.ndarray,
                      direction: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half the difference of the two directions' mean errors, per point, from within-group pairs only
    (a group's offset cancels in its own difference), pooled over groups with inverse-variance weights.

    Returns
    -------
    x_mean, half, weight : per point that some group approached from both sides, sorted by x
    """
    xs, halves, weights = [], [], []
    for label in np.unique(point):
        at = point == label
        sums = np.zeros(2)
        for g in np.unique(group[at]):
            cell = at & (group == g)
            up, down = cell & (direction == 1), cell & (direction == -1)
            if up.any() and down.any():
                w = 4.0 / (1.0 / up.sum() + 1.0 / down.sum())
                sums += (w * 0.5 * (error[up].mean() - error[down].mean()), w)
        if sums[1] > 0:
            xs.append(x[at].mean())
            halves.append(sums[0] / sums[1])
            weights.append(sums[1])
    order = np.argsort(xs)
    return np.asarray(xs)[order], np.asarray(halves)[order], np.asarray(weights)[order]


def _hysteresis_curve(x: np.ndarray, half: np.ndarray, weight: np.ndarray) -> SplineCurve | PolynomialCurve:
    if x.size >= 3:
        return fit_spline_curve(x, half, weight)
    value = float(np.average(half, weights=weight))
    return PolynomialCurve(float(x.mean()), 1.0, np.array([value]))


def aligned_points(data: CalibrationData, align: bool = True) -> AlignedPoints:
    """Hysteresis (when bidirectional), group alignment (paper step 3) and point means (step 4).

    Parameters
    ----------
    data : CalibrationData
    align : estimate group offsets (False: every offset 0)

    Returns
    -------
    AlignedPoints
        Point means of the error with each observation's hysteresis share d·h(x) removed (so
        mid-way between the directions) and its group's offset added.

    Notes
    -----
    The hysteresis comes from within-group differences only: a group's offset cancels there, so
    offsets and hysteresis cannot bias each other. A calibration whose groups each approach from
    one direction only (but not all the same) cannot tell them apart and is refused. The result is
    computed once per data set and shared (``calibrate`` fits every method on the same folds).
    """
    if data.n_points < MIN_POINTS:
        raise ValueError(f"{data.component}: need at least {MIN_POINTS} distinct calibration points, "
                         f"got {data.n_points}")
    direction = np.zeros(0) if data.direction is None else data.direction
    key = digest(data.measured, data.reference, data.group, data.point, direction, align)
    return _ALIGNED.get(key, lambda: _aligned_points(data, align))


_ALIGNED: Memo[AlignedPoints] = Memo()


def _aligned_points(data: CalibrationData, align: bool) -> AlignedPoints:
    x, e, g, p = data.measured, data.error, data.group, data.point
    hysteresis: SplineCurve | PolynomialCurve | None = None
    if data.direction is not None and data.bidirectional:
        hx, half, hw = _half_differences(x, e, g, p, data.direction)
        if hx.size == 0:
            raise ValueError(f"{data.component}: every group approaches from one direction only, so group offsets "
                             "and hysteresis cannot be told apart; approach from both directions within a group")
        hysteresis = _hysteresis_curve(hx, half, hw)
        e = e - data.direction * hysteresis.predict(x)
    alignment = align_groups(x, e, g, p) if align else GroupAlignment.identity(g)
    xm, em, wm, _ = point_means(x, alignment.apply(e, g), p)
    try:
        floor: float | None = data_noise_floor(data)
    except ValueError:
        floor = None
    return AlignedPoints(xm, em, wm, alignment, hysteresis, floor)


class Compensator(ABC):
    """Fits an error model of one component from calibration data."""

    name: str = "compensator"
    align: bool = True
    model_direction: bool = True

    def fit(self, data: CalibrationData) -> FittedModel:
        """Fit the error model.

        Parameters
        ----------
        data : CalibrationData
            Measured and reference values (the error is derived), groups, points, directions.

        Returns
        -------
        FittedModel
        """
        if not isinstance(data, CalibrationData):
            raise TypeError(f"{type(self).__name__}.fit takes CalibrationData (measured + reference), "
                            f"got {type(data).__name__}")
        started = time.perf_counter()
        points = aligned_points(data, self.align)
        curve, details = self._fit_curve(points.x, points.error, points.weight, points.noise_sigma)
        hysteresis = points.hysteresis if self.model_direction else None
        details = {**details, "fit_seconds": time.perf_counter() - started, "n_points": int(points.x.size),
                   "n_observations": int(data.measured.size)}
        return FittedModel(self.name, curve, points.alignment,
                           (float(data.measured.min()), float(data.measured.max())), data.directions, hysteresis,
                           details)

    @abstractmethod
    def _fit_curve(self, x: np.ndarray, y: np.ndarray, w: np.ndarray, noise_sigma: float | None
                   ) -> tuple[Curve, dict]:
        """Curve through aligned point means (sorted x, mean error, repeat weight, noise σ or None)."""


class NoCompensation(Compensator):
    """Predicts zero error (the raw instrument)."""

    name = "none"
    align = False
    model_direction = False

    def _fit_curve(self, x: np.ndarray, y: np.ndarray, w: np.ndarray, noise_sigma: float | None
                   ) -> tuple[Curve, dict]:
        return ZeroCurve(), {}


class SmoothingSplineCompensator(Compensator):
    """CSF alone: smoothing spline with λ by GCV (or leave-one-point-out) on a log grid.

    Parameters
    ----------
    criterion : "gcv" or "loo"
    trend_degree : polynomial fitted first (0: none)
    end_curvature : unpenalised u² term, so the ends may bend (natural end conditions otherwise
        force zero curvature there)
    name : defaults to "csf", "csf+poly<d>" or "csf+ends"
    """

    def __init__(self, criterion: str = "gcv", trend_degree: int = 0, end_curvature: bool = False,
                 name: str | None = None):
        self.criterion, self.trend_degree, self.end_curvature = criterion, trend_degree, end_curvature
        default = "csf" if trend_degree == 0 else f"csf+poly{trend_degree}"
        self.name = name or (default + ("+ends" if end_curvature else ""))

    def _fit_curve(self, x: np.ndarray, y: np.ndarray, w: np.ndarray, noise_sigma: float | None
                   ) -> tuple[Curve, dict]:
        c = fit_spline_curve(x, y, w, criterion=self.criterion, trend_degree=self.trend_degree,
                             end_curvature=self.end_curvature)
        return c, {"lambda": c.lam, "effective_dof": c.effective_dof, "criterion": self.criterion}


class RippleSplineCompensator(Compensator):
    """CSF with end curvature plus ripples: sinusoids of 2.5–8 grid steps whose periods the
    leave-one-point-out search finds and keeps only on evidence (``instrument.compensation._ripple``).

    Parameters
    ----------
    max_ripples : at most this many (a fundamental and a harmonic by default)
    name : defaults to "csf+ripple"
    """

    def __init__(self, max_ripples: int = MAX_RIPPLES, name: str = "csf+ripple"):
        self.max_ripples, self.name = max_ripples, name

    def _fit_curve(self, x: np.ndarray, y: np.ndarray, w: np.ndarray, noise_sigma: float | None
                   ) -> tuple[Curve, dict]:
        c = fit_ripple_spline(x, y, w, noise_variance=None if noise_sigma is None else noise_sigma**2,
                              max_ripples=self.max_ripples)
        step = float(np.median(np.diff(np.sort(x))))
        return c, {"lambda": c.lam, "effective_dof": c.effective_dof,
                   "ripple_periods_steps": (c.ripple_periods / step).tolist()}


class PolynomialCompensator(Compensator):
    """Low-order polynomial; degree by leave-one-point-out error (or fixed)."""

    def __init__(self, degree: int | None = None, max_degree: int = 5, name: str = "polynomial"):
        self.degree, self.max_degree, self.name = degree, max_degree, name

    def _fit_curve(self, x: np.ndarray, y: np.ndarray, w: np.ndarray, noise_sigma: float | None
                   ) -> tuple[Curve, dict]:
        c = fit_polynomial(x, y, w, degree=self.degree, max_degree=self.max_degree)
        return c, {"degree": int(c.coefficients.size - 1)}


class GaussianProcessCompensator(Compensator):
    """Gaussian process (squared-exponential kernel on a linear trend, length scale ≥ grid step)."""

    name = "gaussian_process"

    def _fit_curve(self, x: np.ndarray, y: np.ndarray, w: np.ndarray, noise_sigma: float | None
                   ) -> tuple[Curve, dict]:
        c = fit_gaussian_process(x, y, w, point_variance=None if noise_sigma is None else noise_sigma**2)
        return c, {"length_scale": c.length_scale, "signal_variance": c.signal_variance,
                   "noise_variance": c.noise_variance}


class CsfPpsoEsnCompensator(Compensator):
    """The paper's CSF-PPSO-ESN (§3.4): CSF per group → group alignment → PPSO-tuned CSF + ESN.

    Parameters
    ----------
    seed : seeds the reservoirs and the swarm (deterministic for a fixed seed)
    n_particles, n_iterations, archive_size : PPSO budget
    selection : how the Pareto front's member is chosen (``SELECTIONS``; default "one_se")
    ripples : let the spline part carry the ripples the ripple search keeps (issue 25)
    name : defaults to "csf-ppso-esn"
    """

    def __init__(self, *, seed: int = 0, n_particles: int = 12, n_iterations: int = 15, archive_size: int = 30,
                 selection: str = "one_se", ripples: bool = True, name: str | None = None):
        if selection not in SELECTIONS:
            raise ValueError(f"selection must be one of {SELECTIONS}, got {selection!r}")
        self.seed, self.n_particles, self.n_iterations = seed, n_particles, n_iterations
        self.archive_size, self.selection, self.ripples = archive_size, selection, ripples
        self.name = name or "csf-ppso-esn"

    def _fit_curve(self, x: np.ndarray, y: np.ndarray, w: np.ndarray, noise_sigma: float | None
                   ) -> tuple[Curve, dict]:
        tuning = tune_csf_esn(x, y, w, seed=self.seed, n_particles=self.n_particles, n_iterations=self.n_iterations,
                              archive_size=self.archive_size, selection=self.selection,
                              noise_variance=None if noise_sigma is None else noise_sigma**2, ripples=self.ripples)
        curve = tuning.curve
        details = {
            "hyperparameters": curve.hyper.to_dict(),
            "selection": self.selection,
            "chosen": {"train_rms": tuning.train_rms, "heldout_rms": tuning.heldout_rms, "effective_dof": tuning.dof},
            "ripple_periods_steps": (2 * np.pi / (curve.ripple_omegas * float(np.median(np.diff(curve.knots_u)))
                                     )).tolist(),
            "pareto_front_si": (tuning.front.objectives * curve.y_scale).tolist(),
            "ppso_evaluations": int(tuning.front.n_evaluations),
        }
        return curve, details


def default_compensators(*, seed: int = 0) -> dict[str, Compensator]:
    """The paper's method and every baseline, keyed by name.

    Parameters
    ----------
    seed : seeds CSF-PPSO-ESN

    Returns
    -------
    dict name → Compensator: "csf-ppso-esn", "csf", "csf+ripple", "polynomial", "gaussian_process", "none"
    """
    methods: list[Compensator] = [
        CsfPpsoEsnCompensator(seed=seed),
        SmoothingSplineCompensator(),
        RippleSplineCompensator(),
        PolynomialCompensator(),
        GaussianProcessCompensator(),
        NoCompensation(),
    ]
    return {m.name: m for m in methods}
