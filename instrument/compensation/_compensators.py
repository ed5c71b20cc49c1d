"""Compensators: one interface, the paper's CSF-PPSO-ESN and the baselines.

``Compensator.fit(measured, error, groups=None, points=None) -> FittedModel`` runs the paper's
four steps (§3.4) for every method except ``none``:

1. the observations arrive as (measured, error = measured − reference, group, point);
2. a CSF (smoothing spline) curve is fitted per group;
3. groups are aligned onto the first group's curve by one offset each, estimated in the interval
   where that curve varies least (``GroupAlignment``);
4. repeats are averaged at each calibration point and the method's curve is fitted to the
   aligned point means (CSF-PPSO-ESN: the PPSO-tuned ESN; baselines: their own curve).

``FittedModel.predict(measured)`` returns the predicted error in the reference group's frame;
the corrected value is ``measured − predict(measured)``.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from instrument.compensation._align import GroupAlignment, align_groups
from instrument.compensation._baselines import (
    GaussianProcessCurve,
    PolynomialCurve,
    ZeroCurve,
    fit_gaussian_process,
    fit_polynomial,
)
from instrument.compensation._data import infer_points, noise_floor, point_means
from instrument.compensation._esn import EsnCurve, fit_esn, tune_esn
from instrument.compensation._spline import SplineCurve, fit_spline_curve

CURVE_KINDS = {c.kind: c for c in (ZeroCurve, SplineCurve, PolynomialCurve, GaussianProcessCurve, EsnCurve)}


@dataclass(frozen=True)
class SumCurve:
    """Sum of two curves (a base curve plus a learned residual correction)."""

    base: object
    residual: object

    kind = "sum"

    def predict(self, x):
        return self.base.predict(x) + self.residual.predict(x)

    def to_dict(self) -> dict:
        return {"kind": self.kind, "base": self.base.to_dict(), "residual": self.residual.to_dict()}

    @classmethod
    def from_dict(cls, d: dict) -> SumCurve:
        return cls(curve_from_dict(d["base"]), curve_from_dict(d["residual"]))


CURVE_KINDS[SumCurve.kind] = SumCurve


def curve_from_dict(d: dict):
    try:
        return CURVE_KINDS[d["kind"]].from_dict(d)
    except KeyError as exc:
        raise ValueError(f"unknown or incomplete curve description: missing {exc}") from None


@dataclass(frozen=True)
class FittedModel:
    """A fitted error model of one component.

    Attributes
    ----------
    method : name of the compensator that made it
    curve : the error curve (``predict(x)``)
    alignment : group offsets found in step 3 (relative to the reference group)
    validity : (lo, hi) range of the measured values it was fitted on
    details : JSON-able facts about the fit (chosen hyper-parameters, Pareto front, timings)
    """

    method: str
    curve: object
    alignment: GroupAlignment
    validity: tuple
    details: dict = field(default_factory=dict)

    def predict(self, measured):
        """Predicted error at ``measured`` (same unit); corrected value = measured − this."""
        return self.curve.predict(np.asarray(measured, float))

    def group_offset(self, group: int) -> float:
        return self.alignment.offset(group)

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "curve": self.curve.to_dict(),
            "alignment": self.alignment.to_dict(),
            "validity": [float(self.validity[0]), float(self.validity[1])],
            "details": self.details,
        }

    @classmethod
    def from_dict(cls, d: dict) -> FittedModel:
        return cls(str(d["method"]), curve_from_dict(d["curve"]), GroupAlignment.from_dict(d["alignment"]),
                   (float(d["validity"][0]), float(d["validity"][1])), dict(d.get("details", {})))


def _prepare(measured, error, groups, points):
    x = np.asarray(measured, float).ravel()
    e = np.asarray(error, float).ravel()
    if x.shape != e.shape or x.size == 0:
        raise ValueError(f"measured and error must be non-empty and of one length; got {x.size} and {e.size}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(e))):
        raise ValueError("measured and error must be finite")
    g = np.zeros(x.size, int) if groups is None else np.asarray(groups).ravel().astype(int)
    p = infer_points(x) if points is None else np.asarray(points).ravel().astype(int)
    if g.size != x.size or p.size != x.size:
        raise ValueError("groups and points must have one label per observation")
    if np.unique(p).size < 4:
        raise ValueError(f"need at least 4 distinct calibration points, got {np.unique(p).size}")
    return x, e, g, p


class Compensator(ABC):
    """Fits an error model of one component from calibration observations."""

    name: str = "compensator"
    align: bool = True

    def fit(self, measured, error, groups=None, points=None) -> FittedModel:
        """Fit the error model.

        Parameters
        ----------
        measured : (n,) measured values (m or rad)
        error : (n,) measured − reference
        groups : (n,) calibration group labels, or None for one group
        points : (n,) calibration point labels, or None to cluster the measured values
        """
        started = time.perf_counter()
        x, e, g, p = _prepare(measured, error, groups, points)
        alignment = align_groups(x, e, g, p) if self.align else GroupAlignment.identity(g)
        aligned = alignment.apply(e, g)
        xm, em, wm, _ = point_means(x, aligned, p)
        try:
            floor = noise_floor(aligned, g, p)
        except ValueError:
            floor = None
        curve, details = self._fit_curve(xm, em, wm, floor)
        details = {**details, "fit_seconds": time.perf_counter() - started, "n_points": int(xm.size),
                   "n_observations": int(x.size)}
        return FittedModel(self.name, curve, alignment, (float(x.min()), float(x.max())), details)

    @abstractmethod
    def _fit_curve(self, x, y, w, noise_sigma):
        """Curve through aligned point means (sorted x, mean error, repeat count, noise σ or None)."""


class NoCompensation(Compensator):
    """Predicts zero error (the raw instrument)."""

    name = "none"
    align = False

    def _fit_curve(self, x, y, w, noise_sigma):
        return ZeroCurve(), {}


class SmoothingSplineCompensator(Compensator):
    """CSF alone: smoothing spline with λ by GCV (or leave-one-point-out) on a log grid."""

    def __init__(self, criterion: str = "gcv", trend_degree: int = 0, name: str | None = None):
        self.criterion, self.trend_degree = criterion, trend_degree
        self.name = name or ("csf" if trend_degree == 0 else f"csf+poly{trend_degree}")

    def _fit_curve(self, x, y, w, noise_sigma):
        c = fit_spline_curve(x, y, w, criterion=self.criterion, trend_degree=self.trend_degree)
        return c, {"lambda": c.lam, "effective_dof": c.effective_dof, "criterion": self.criterion}


class PolynomialCompensator(Compensator):
    """Low-order polynomial; degree by leave-one-point-out error (or fixed)."""

    def __init__(self, degree: int | None = None, max_degree: int = 5, name: str = "polynomial"):
        self.degree, self.max_degree, self.name = degree, max_degree, name

    def _fit_curve(self, x, y, w, noise_sigma):
        c = fit_polynomial(x, y, w, degree=self.degree, max_degree=self.max_degree)
        return c, {"degree": int(c.coefficients.size - 1)}


class GaussianProcessCompensator(Compensator):
    """Gaussian process (squared-exponential kernel, length scale ≥ grid step)."""

    name = "gaussian_process"

    def _fit_curve(self, x, y, w, noise_sigma):
        c = fit_gaussian_process(x, y, w, point_variance=None if noise_sigma is None else noise_sigma**2)
        return c, {"length_scale": c.length_scale, "signal_variance": c.signal_variance,
                   "noise_variance": c.noise_variance}


class CsfPpsoEsnCompensator(Compensator):
    """The paper's CSF-PPSO-ESN (§3.4): CSF per group → group alignment → PPSO-tuned ESN.

    Parameters
    ----------
    seed : seeds the reservoir and the swarm (deterministic for a fixed seed)
    n_particles, n_iterations, archive_size : PPSO budget
    selection : "knee" (the knee of the Pareto front, default) or "min_heldout"
    residual_of_csf : when True the ESN learns what the CSF curve leaves (CSF + ESN correction);
        the paper's step 4 (default False) feeds the aligned data to the ESN directly.
    """

    def __init__(self, *, seed: int = 0, n_particles: int = 16, n_iterations: int = 30, archive_size: int = 30,
                 selection: str = "knee", residual_of_csf: bool = False, name: str | None = None):
        if selection not in ("knee", "min_heldout"):
            raise ValueError(f"selection must be 'knee' or 'min_heldout', got {selection!r}")
        self.seed, self.n_particles, self.n_iterations = seed, n_particles, n_iterations
        self.archive_size, self.selection, self.residual_of_csf = archive_size, selection, residual_of_csf
        self.name = name or ("csf-ppso-esn" if not residual_of_csf else "csf+ppso-esn-residual")

    def _fit_curve(self, x, y, w, noise_sigma):
        base = None
        target = y
        if self.residual_of_csf:
            base = fit_spline_curve(x, y, w)
            target = y - base.predict(x)
        hyper, front = tune_esn(x, target, seed=self.seed, n_particles=self.n_particles,
                                n_iterations=self.n_iterations, archive_size=self.archive_size)
        if self.selection == "min_heldout":
            from instrument.compensation._esn import decode

            hyper = decode(front.positions[int(np.argmin(front.objectives[:, 1]))])
        curve = fit_esn(x, target, hyper, seed=self.seed)
        if base is not None:
            curve = SumCurve(base, curve)
        details = {
            "hyperparameters": hyper.to_dict(),
            "selection": self.selection,
            "pareto_front": front.objectives.tolist(),
            "ppso_evaluations": int(front.n_evaluations),
        }
        return curve, details


def default_compensators(*, seed: int = 0, fast: bool = False) -> dict:
    """The paper's method and every baseline, keyed by name."""
    budget = dict(n_particles=10, n_iterations=12) if fast else {}
    methods = [
        CsfPpsoEsnCompensator(seed=seed, **budget),
        SmoothingSplineCompensator(),
        PolynomialCompensator(),
        GaussianProcessCompensator(),
        NoCompensation(),
    ]
    return {m.name: m for m in methods}
