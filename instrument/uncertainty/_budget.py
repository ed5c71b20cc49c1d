"""The uncertainty budget: its terms, how each one is correlated, and builders for the usual ones.

A term is one source of measurement error with its standard uncertainty per pose component
[x, y, z, a, b, c] (m and rad; a relative number for a scale term) and the way its error is shared
between the poses of a run (``Correlation``): the Monte Carlo draws one value per pose, per point,
per run, or one relative error for the run that multiplies the coordinate. That sharing decides
which figures a term can move: a per-run offset cannot move a repeatability, a per-point error
cancels in a multi-directional variation, per-pose noise inflates every spread.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from enum import StrEnum
from typing import Any

import numpy as np

from instrument._conventions import COMPONENTS
from instrument.uncertainty._errors import UncertaintyError

MINIMUM_DOF = 3.0  # below this the spread of a Type A standard deviation has no finite variance


class Correlation(StrEnum):
    """How a term's error is shared between the measured poses of a run."""

    POSE = "pose"  # independent for every measured pose (frame noise)
    POINT = "point"  # systematic at a point: a smooth function of the component's value (a calibration curve)
    RUN = "run"  # one offset for the whole run, on the tool pose (transform fit, environment)
    SCALE = "scale"  # one relative error for the whole run, times the OPR coordinate (reference scale)


class Distribution(StrEnum):
    """Shape of a term's error for a given standard uncertainty u."""

    NORMAL = "normal"
    RECTANGULAR = "rectangular"  # uniform on ±√3·u


Range = tuple[float, float]


@dataclass(frozen=True)
class BudgetTerm:
    """One line of the budget.

    Attributes
    ----------
    name : str
        Short, unique within a budget (it keys the per-figure contributions).
    source : str
        Where the number comes from and how it was estimated, for the report.
    correlation : Correlation
    standard_uncertainty : tuple of 6 floats
        Per component x, y, z (m), a, b, c (rad); relative (m/m, rad/rad) for a SCALE term. Zero
        where the term does not act.
    distribution : Distribution
    dof : float
        Degrees of freedom of the estimate (``inf`` for a Type B value). With finite dof each
        Monte Carlo draw first draws the term's σ from its scaled inverse-χ² distribution
        (JCGM 101 §6.4.9 for a Type A standard deviation), which widens the output's tails.
    correlation_length : tuple of 6 (float or None), optional
        POINT terms: the error is a smooth function of the component's value whose correlation
        falls as exp(−Δ²/2ℓ²) (ℓ in m or rad, typically the calibration step); None: independent
        at every point (poses of the same point share it).
    validity : tuple of 6 (lo, hi) or None, optional
        POINT terms: the component range inside which ``standard_uncertainty`` holds (the
        calibration's validity range). A point beyond it by d gets u·(outside_factor + d/ℓ).
    outside_factor : float
    shared : bool
        RUN and SCALE terms: one draw shared by all components (a common scale error) instead of
        one per component.
    """

    name: str
    source: str
    correlation: Correlation
    standard_uncertainty: tuple[float, ...]
    distribution: Distribution = Distribution.NORMAL
    dof: float = math.inf
    correlation_length: tuple[float | None, ...] | None = None
    validity: tuple[Range | None, ...] | None = None
    outside_factor: float = 2.0
    shared: bool = False

    def __post_init__(self) -> None:
        where = f"term {self.name!r}"
        if not self.name:
            raise UncertaintyError("budget term: needs a name")
        object.__setattr__(self, "correlation", _enum(Correlation, self.correlation, f"{where}: correlation"))
        object.__setattr__(self, "distribution", _enum(Distribution, self.distribution, f"{where}: distribution"))
        u = per_component(self.standard_uncertainty, f"{where}: standard_uncertainty")
        if any(v < 0 for v in u):
            raise UncertaintyError(f"{where}: standard_uncertainty must be ≥ 0, got {list(u)}")
        object.__setattr__(self, "standard_uncertainty", u)
        dof = float(self.dof)
        if not dof >= MINIMUM_DOF:  # also refuses NaN
            raise UncertaintyError(f"{where}: dof must be ≥ {MINIMUM_DOF:g} (or inf), got {self.dof}")
        object.__setattr__(self, "dof", dof)
        if self.correlation_length is not None:
            lengths = _optional_per_component(self.correlation_length, f"{where}: correlation_length")
            if any(v is not None and not v > 0 for v in lengths):
                raise UncertaintyError(f"{where}: correlation_length must be > 0, got {list(lengths)}")
            object.__setattr__(self, "correlation_length", lengths)
        if self.validity is not None:
            object.__setattr__(self, "validity", _ranges(self.validity, f"{where}: validity"))
        if not float(self.outside_factor) >= 1.0:
            raise UncertaintyError(f"{where}: outside_factor must be ≥ 1, got {self.outside_factor}")
        if self.correlation is not Correlation.POINT and (self.validity is not None or self.correlation_length):
            raise UncertaintyError(f"{where}: validity and correlation_length apply to point terms only")

    @property
    def active(self) -> bool:
        """True when the term acts on at least one component."""
        return any(v > 0 for v in self.standard_uncertainty)

    def beyond_validity(self, values: np.ndarray) -> np.ndarray:
        """(..., 6) component values → (..., 6) distance beyond the validity range (0 inside)."""
        values = np.asarray(values, dtype=float)
        distance = np.zeros_like(values)
        for k, bounds in enumerate(self.validity or ()):
            if bounds is not None:
                lo, hi = bounds
                distance[..., k] = np.maximum(lo - values[..., k], 0.0) + np.maximum(values[..., k] - hi, 0.0)
        return distance

    def uncertainty_at(self, values: np.ndarray) -> np.ndarray:
        """(..., 6) component values → (..., 6) standard uncertainty there (inflated beyond validity)."""
        values = np.asarray(values, dtype=float)
        u = np.broadcast_to(np.array(self.standard_uncertainty), values.shape).copy()
        distance = self.beyond_validity(values)
        outside = distance > 0
        if outside.any():
            lengths = np.array([np.inf if v is None else v for v in (self.correlation_length or (None,) * 6)])
            factor = self.outside_factor + distance / np.broadcast_to(lengths, values.shape)
            u = np.where(outside, u * factor, u)
        return u

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (SI; relative for a scale term)."""
        return {
            "name": self.name,
            "source": self.source,
            "correlation": self.correlation.value,
            "distribution": self.distribution.value,
            "standard_uncertainty": dict(zip(COMPONENTS, self.standard_uncertainty)),
            "unit": "relative" if self.correlation is Correlation.SCALE else "m (x, y, z), rad (a, b, c)",
            "dof": None if math.isinf(self.dof) else self.dof,
            "correlation_length": None if self.correlation_length is None
            else dict(zip(COMPONENTS, self.correlation_length)),
            "validity": None if self.validity is None
            else {c: None if r is None else list(r) for c, r in zip(COMPONENTS, self.validity)},
            "outside_factor": self.outside_factor,
            "shared": self.shared,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> BudgetTerm:
        """Inverse of ``to_dict``."""
        try:
            lengths = data.get("correlation_length")
            validity = data.get("validity")
            return cls(
                name=data["name"],
                source=data.get("source", ""),
                correlation=data["correlation"],
                standard_uncertainty=per_component(data["standard_uncertainty"], "standard_uncertainty"),
                distribution=data.get("distribution", "normal"),
                dof=math.inf if data.get("dof") is None else data["dof"],
                correlation_length=None if lengths is None else _optional_per_component(lengths, "correlation_length"),
                validity=None if validity is None else _ranges(validity, "validity"),
                outside_factor=data.get("outside_factor", 2.0),
                shared=bool(data.get("shared", False)),
            )
        except KeyError as exc:
            raise UncertaintyError(f"budget term: missing field {exc.args[0]!r}") from None


@dataclass(frozen=True)
class UncertaintyBudget:
    """The terms of one run's budget (names unique)."""

    terms: tuple[BudgetTerm, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        terms = tuple(self.terms)
        for term in terms:
            if not isinstance(term, BudgetTerm):
                raise UncertaintyError(f"budget: expected BudgetTerm entries, got {type(term).__name__}")
        names = [t.name for t in terms]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise UncertaintyError(f"budget: term names must be unique, repeated: {', '.join(duplicates)}")
        object.__setattr__(self, "terms", terms)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(t.name for t in self.terms)

    def only(self, name: str) -> UncertaintyBudget:
        """The budget reduced to one term (for its contribution)."""
        return UncertaintyBudget(tuple(t for t in self.terms if t.name == name))

    def with_term(self, term: BudgetTerm) -> UncertaintyBudget:
        """A copy with ``term`` added, or replacing the term of the same name."""
        return UncertaintyBudget(tuple(t for t in self.terms if t.name != term.name) + (term,))

    def to_dict(self) -> dict[str, Any]:
        return {"terms": [t.to_dict() for t in self.terms]}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> UncertaintyBudget:
        return cls(tuple(BudgetTerm.from_dict(t) for t in data.get("terms", ())))


# -- builders for the usual terms ------------------------------------------------------------------


def compensation_term(
    heldout_rms: Mapping[str, float],
    *,
    noise_floor: Mapping[str, float] | None = None,
    observations_per_point: int = 9,
    validity: Mapping[str, Range] | None = None,
    correlation_length: Mapping[str, float] | None = None,
    outside_factor: float = 2.0,
    dof: float = math.inf,
    source: str = "calibration record: held-out RMS per component",
) -> BudgetTerm:
    """The compensation's residual error: systematic at a point, a function of the measured value.

    Parameters
    ----------
    heldout_rms : mapping component → held-out RMS h of the compensated error (m or rad), from the
        calibration record's evaluation. Each held-out observation also carries its own noise.
    noise_floor : mapping component → the calibration's noise floor f (repeat scatter), optional.
        Given, the noise of the held-out observations is removed in quadrature, since the run's own
        noise is a separate term: u = √max(h² − f², f²/m), never below the noise that a curve
        fitted to m = ``observations_per_point`` observations per point keeps. Without it u = h
        (conservative: the noise is counted twice).
    observations_per_point : int, repeats × groups at each calibration point (3 × 3 = 9)
    validity : mapping component → (lo, hi), the record's validity range (measured values).
    correlation_length : mapping component → ℓ (m or rad): how far apart two values must be for
        the curve's residuals to decorrelate; the calibration step is a natural choice.
    outside_factor : float
        Beyond the validity range by d, u becomes u·(outside_factor + d/ℓ) (a convention: the
        correction is extrapolated linearly there and no held-out evidence exists).
    dof : float, degrees of freedom of h (about the number of held-out calibration points)
    """
    lengths = None if correlation_length is None else _optional_per_component(correlation_length, "correlation_length")
    ranges = None if validity is None else _ranges(validity, "validity")
    heldout = np.array(per_component(heldout_rms, "heldout_rms"))
    if noise_floor is not None:
        floor = np.array(per_component(noise_floor, "noise_floor"))
        if int(observations_per_point) < 1:
            raise UncertaintyError(f"observations_per_point: expected ≥ 1, got {observations_per_point}")
        heldout = np.sqrt(np.maximum(heldout**2 - floor**2, floor**2 / int(observations_per_point)))
        source += ", less the noise floor in quadrature"
    return BudgetTerm("compensation residual", source, Correlation.POINT, tuple(float(v) for v in heldout),
                      correlation_length=lengths, validity=ranges, outside_factor=outside_factor, dof=dof)


def interferometer_terms(
    scale_uncertainty: float,
    noise: float,
    *,
    correlation_length: float | None = None,
    scale_distribution: Distribution | str = Distribution.RECTANGULAR,
) -> tuple[BudgetTerm, BudgetTerm]:
    """The displacement reference: its scale error (common to x, y, z) and its noise.

    Parameters
    ----------
    scale_uncertainty : float
        Standard uncertainty of the interferometer's scale (relative: 0.5e-6 for 0.5 ppm), e.g. the
        wavelength compensation's residual; a manufacturer's ±a ppm is a rectangular u = a/√3.
    noise : float
        Standard uncertainty (m) of one averaged reference reading at a calibration point; it went
        into the calibration curve, so it is systematic at a point.
    correlation_length : float, optional
        ℓ (m) of the noise term; None: independent at every point.
    """
    length = None if correlation_length is None else (correlation_length,) * 3 + (None,) * 3
    scale = BudgetTerm("interferometer scale", "interferometer specification / wavelength compensation",
                       Correlation.SCALE, (scale_uncertainty,) * 3 + (0.0,) * 3,
                       distribution=Distribution(scale_distribution), shared=True)
    reading = BudgetTerm("interferometer noise", "interferometer reading noise, averaged at each calibration point",
                         Correlation.POINT, (noise,) * 3 + (0.0,) * 3, correlation_length=length)
    return scale, reading


def rotary_table_term(encoder_uncertainty: float, *, correlation_length: float | None = None,
                      distribution: Distribution | str = Distribution.RECTANGULAR) -> BudgetTerm:
    """The angle reference: the table encoder's error (rad) at the angle a calibration point used.

    A specification of ±e (e.g. ±0.5″) is a rectangular u = e/√3; the error depends on the angle,
    so it is systematic at a point (ℓ: how far apart two angles must be for it to decorrelate).
    """
    length = None if correlation_length is None else (None,) * 3 + (correlation_length,) * 3
    return BudgetTerm("rotary table encoder", "rotary table specification", Correlation.POINT,
                      (0.0,) * 3 + (encoder_uncertainty,) * 3, distribution=Distribution(distribution),
                      correlation_length=length)


def transform_term(residual_rms: float, n_points: int, *, spread: float, lever: float = 0.0) -> BudgetTerm:
    """The end-effector (registration) transform's fit error, common to the whole run.

    From a rigid (Kabsch) fit of ``n_points`` point pairs with 3-D residual RMS r: per-coordinate
    noise σ² = n·r²/(3n − 6); the fitted translation at the points' centroid has u = σ/√n per
    axis and the rotation u_φ ≈ σ/(√n·ρ) (ρ = ``spread``, the RMS distance of the fit points from
    their centroid). At ``lever`` L from the centroid: u_pos = σ/√n·√(1 + (L/ρ)²). An
    approximation for points spread about evenly in three dimensions.
    """
    n = int(n_points)
    if n < 3:
        raise UncertaintyError(f"transform_term: a rigid fit needs ≥ 3 points, got {n_points}")
    if not spread > 0:
        raise UncertaintyError(f"transform_term: spread must be > 0 m, got {spread}")
    sigma = math.sqrt(n * residual_rms**2 / (3 * n - 6)) if n > 2 else 0.0
    u_position = sigma / math.sqrt(n) * math.sqrt(1.0 + (lever / spread) ** 2)
    u_angle = sigma / (math.sqrt(n) * spread)
    return BudgetTerm("transform fit", f"rigid fit of {n} points, residual RMS {residual_rms:.3g} m",
                      Correlation.RUN, (u_position,) * 3 + (u_angle,) * 3, dof=max(3 * n - 6, MINIMUM_DOF))


def environment_term(temperature_deviation: float, expansion_coefficient: float, lever: float, *,
                     temperature_uncertainty: float = 0.0) -> BudgetTerm:
    """Thermal expansion of the measuring loop, uncorrected: one offset per axis for the run.

    The error α·ΔT·L lies anywhere in ±α·|ΔT|·L (the loop's geometry decides the sign and share),
    a rectangular u = α·|ΔT|·L/√3, combined with the thermometer's u_T: u = α·L·√(ΔT²/3 + u_T²).

    Parameters
    ----------
    temperature_deviation : float, K, recorded temperature − 20 °C (or the calibration's temperature)
    expansion_coefficient : float, 1/K (steel 11.5e-6, aluminium 23e-6)
    lever : float, m, length of the structural loop between the sensor module and the robot base
    temperature_uncertainty : float, K, standard uncertainty of the recorded temperature
    """
    u = abs(expansion_coefficient) * abs(lever) * math.sqrt(temperature_deviation**2 / 3 + temperature_uncertainty**2)
    distribution = Distribution.RECTANGULAR if temperature_uncertainty == 0 else Distribution.NORMAL
    source = (f"ΔT = {temperature_deviation:.3g} K (u_T {temperature_uncertainty:.3g} K), "
              f"α = {expansion_coefficient:.3g} /K, lever {lever:.3g} m")
    return BudgetTerm("environment", source, Correlation.RUN, (u, u, u, 0.0, 0.0, 0.0), distribution=distribution)


def scaled(term: BudgetTerm, factor: float) -> BudgetTerm:
    """The same term with its standard uncertainty multiplied by ``factor`` (sensitivity studies)."""
    return replace(term, standard_uncertainty=tuple(v * factor for v in term.standard_uncertainty))


# -- input normalisation ---------------------------------------------------------------------------


def per_component(values: Mapping[str, float] | Sequence[float] | np.ndarray, name: str) -> tuple[float, ...]:
    """A mapping {component: value} (missing → 0) or 6 values → a tuple of 6 finite floats."""
    if isinstance(values, Mapping):
        unknown = sorted(set(values) - set(COMPONENTS))
        if unknown:
            raise UncertaintyError(f"{name}: unknown component(s) {', '.join(map(str, unknown))}; use x, y, z, a, b, c")
        out = [values.get(c, 0.0) for c in COMPONENTS]
    else:
        out = list(np.asarray(values, dtype=float).reshape(-1))
        if len(out) != 6:
            raise UncertaintyError(f"{name}: expected 6 values [x, y, z, a, b, c], got {len(out)}")
    try:
        result = tuple(float(v) for v in out)
    except (TypeError, ValueError):
        raise UncertaintyError(f"{name}: expected numbers, got {out}") from None
    if not all(math.isfinite(v) for v in result):
        raise UncertaintyError(f"{name}: values must be finite, got {list(result)}")
    return result


def _optional_per_component(values, name: str) -> tuple[float | None, ...]:
    if isinstance(values, Mapping):
        items = [values.get(c) for c in COMPONENTS]
        unknown = sorted(set(values) - set(COMPONENTS))
        if unknown:
            raise UncertaintyError(f"{name}: unknown component(s) {', '.join(map(str, unknown))}")
    else:
        items = list(values)
        if len(items) != 6:
            raise UncertaintyError(f"{name}: expected 6 values [x, y, z, a, b, c], got {len(items)}")
    try:
        return tuple(None if v is None else float(v) for v in items)
    except (TypeError, ValueError):
        raise UncertaintyError(f"{name}: expected numbers or None, got {items}") from None


def _ranges(values, name: str) -> tuple[Range | None, ...]:
    items = [values.get(c) for c in COMPONENTS] if isinstance(values, Mapping) else list(values)
    if len(items) != 6:
        raise UncertaintyError(f"{name}: expected 6 ranges [x, y, z, a, b, c], got {len(items)}")
    out: list[Range | None] = []
    for component, item in zip(COMPONENTS, items):
        if item is None:
            out.append(None)
            continue
        try:
            lo, hi = (float(v) for v in item)
        except (TypeError, ValueError):
            raise UncertaintyError(f"{name}.{component}: expected (lo, hi), got {item!r}") from None
        if not lo < hi:
            raise UncertaintyError(f"{name}.{component}: expected lo < hi, got ({lo}, {hi})")
        out.append((lo, hi))
    return tuple(out)


def _enum(kind, value, name: str):
    try:
        return kind(value)
    except ValueError:
        choices = ", ".join(m.value for m in kind)
        raise UncertaintyError(f"{name}: expected one of {choices}, got {value!r}") from None
