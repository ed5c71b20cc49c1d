"""Synthetic calibrations with a known truth: the paper-like scenario and the hard campaigns.

Both simulate the paper's design (§3.4 step 1): every group (start pose) visits every nominal
point ``repeats`` times; the stage stops at nominal + jitter (the true value); the reference reads
true + its noise; the instrument reads true + error(true) + group offset + its noise. With
hysteresis the error also depends on the approach direction d = ±1: error + d·h(true)/2, so h is
the full difference between approaching from below and from above.

``hard_campaign`` adds what makes compensation hard and scores it against an oracle: ripples whose
period is a non-integer number of grid steps (3.4–6 steps), curvature at both ends (exponential
bends decaying over 1.3–3 steps, which natural spline end conditions cannot follow), group offsets
of tens of µm, optional hysteresis, and two held-out sets the calibration never saw: off-grid
points in the calibration's own sessions, and a new session from start poses outside the
calibration (offsets beyond every calibration group's). Its other profiles (``HARD_PROFILES``)
bring the fast ripple down to 3.0 steps — encoder eccentricity harmonics, gear ripple — alone,
beside the slower terms, or as a fundamental with its second harmonic. The grid's Nyquist limit
is a period of 2 steps: 3 steps is resolvable from the grid alone, but only by a model that can
hold a sinusoid between its points.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from instrument.compensation._data import (
    ARCSEC,
    COMPONENTS,
    LINEAR_COMPONENTS,
    MICROMETRE,
    CalibrationData,
    check_component,
)

ErrorFunction = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class SyntheticScenario:
    """Synthetic calibration sets with their known truth.

    Attributes
    ----------
    data : dict component → CalibrationData
    true_error : dict component → callable(true value) → error of group 0 (the reference group)
    group_offsets : dict component → (n_groups,) array, error offset of each group
    noise_sigma : dict component → standard deviation of one observation's error noise
    """

    data: dict[str, CalibrationData]
    true_error: dict[str, ErrorFunction]
    group_offsets: dict[str, np.ndarray]
    noise_sigma: dict[str, float] = field(default_factory=dict)


def synthetic_calibration(
    component: str,
    nominal: np.ndarray,
    error_function: ErrorFunction,
    *,
    repeats: int = 3,
    group_offsets: tuple[float, ...] | np.ndarray = (0.0,),
    measurement_noise: float,
    reference_noise: float,
    positioning_jitter: float = 0.0,
    hysteresis: ErrorFunction | None = None,
    directions: tuple[int, ...] | None = None,
    rng: np.random.Generator,
) -> CalibrationData:
    """Simulate one calibration: every group visits every nominal point ``repeats`` times per direction.

    Parameters
    ----------
    component : str
    nominal : (p,) array
        Commanded calibration points.
    error_function : callable(true value) → error
    repeats : int
    group_offsets : (g,) offsets added to each group's error
    measurement_noise, reference_noise, positioning_jitter : float
        Standard deviations (SI).
    hysteresis : callable(true value) → h, optional
        Full difference between the two approach directions; the error gains d·h/2.
    directions : tuple of ±1, optional
        Approach directions visited (each with ``repeats`` repeats); None records no direction.
    rng : numpy Generator

    Returns
    -------
    CalibrationData
    """
    nominal = np.asarray(nominal, dtype=float)
    offsets = np.asarray(group_offsets, dtype=float)
    visited = (0,) if directions is None else tuple(directions)
    g, d, p, _ = (a.ravel() for a in np.meshgrid(np.arange(offsets.size), np.array(visited), np.arange(nominal.size),
                                                 np.arange(repeats), indexing="ij"))
    true_value = nominal[p] + (rng.normal(0.0, positioning_jitter, p.size) if positioning_jitter else 0.0)
    reference = true_value + rng.normal(0.0, reference_noise, p.size)
    measured = true_value + error_function(true_value) + offsets[g] + rng.normal(0.0, measurement_noise, p.size)
    if hysteresis is not None:
        measured = measured + d * hysteresis(true_value) / 2.0
    return CalibrationData(component, measured, reference, g, p, None if directions is None else d)


def _paper_like_error(rng: np.random.Generator, lo: float, hi: float, unit: float,
                      amplitudes: tuple[float, float, float]) -> ErrorFunction:
    """A smooth error curve: scale error + quadratic + one periodic term (amplitudes in ``unit``)."""
    linear, quadratic, periodic = amplitudes
    a1 = rng.choice([-1.0, 1.0]) * rng.uniform(0.75, 1.0) * linear * unit
    a2 = rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 1.0) * quadratic * unit
    a3 = rng.uniform(0.5, 1.0) * periodic * unit
    period = rng.uniform(0.45, 0.7) * (hi - lo)
    phase = rng.uniform(0.0, 2 * np.pi)
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)

    def error(v: np.ndarray) -> np.ndarray:
        u = (np.asarray(v, dtype=float) - mid) / half
        return a1 * u + a2 * (u**2 - 1.0 / 3.0) + a3 * np.sin(2 * np.pi * (v - lo) / period + phase)

    return error


def _design(component: str, n_points: int) -> tuple[np.ndarray, float, float, float, float]:
    """Nominal grid, unit, instrument noise, reference noise, positioning jitter (paper §4.2)."""
    if component in LINEAR_COMPONENTS:
        return np.linspace(0.0, 0.070, n_points), MICROMETRE, 0.4 * MICROMETRE, 0.1 * MICROMETRE, 3.0 * MICROMETRE
    return np.deg2rad(np.linspace(-1.75, 1.75, n_points)), ARCSEC, 0.4 * ARCSEC, 0.3 * ARCSEC, 1.0 * ARCSEC


def paper_like_scenario(seed: int = 0, *, n_points: int = 15, repeats: int = 3, n_groups: int = 3
                        ) -> SyntheticScenario:
    """The paper's calibration design (§3.4 step 1, §4.2) with a known, smooth error.

    - x, y, z: 15 points 0–70 mm in 5 mm steps; error scale + quadratic + periodic, up to about
      ±80 µm; instrument noise 0.4 µm, interferometer noise 0.1 µm (1σ); stage positioning
      jitter 3 µm; group offsets 3–8 µm (group 0 has none). The periodic term's period is
      0.45–0.7 of the range (about 6–10 calibration steps).
    - a, b, c: 15 points −1.75° … +1.75° in 0.25° steps (the paper calibrates small rotations on a
      rotary table; it does not print the range); error up to about ±40″; instrument noise 0.4″,
      table noise 0.3″; jitter 1″; group offsets 2–5″.

    Parameters
    ----------
    seed : int
    n_points, repeats, n_groups : int

    Returns
    -------
    SyntheticScenario
    """
    rng = np.random.default_rng(seed)
    data, truth, offsets, sigma = {}, {}, {}, {}
    for component in COMPONENTS:
        nominal, unit, meas, ref, jitter = _design(component, n_points)
        if component in LINEAR_COMPONENTS:
            amplitudes, offset_range = (55.0, 18.0, 6.0), (3.0, 8.0)
        else:
            amplitudes, offset_range = (28.0, 9.0, 3.0), (2.0, 5.0)
        error = _paper_like_error(rng, nominal[0], nominal[-1], unit, amplitudes)
        group_offsets = np.concatenate(
            [[0.0], rng.choice([-1.0, 1.0], n_groups - 1) * rng.uniform(*offset_range, n_groups - 1) * unit]
        )
        data[component] = synthetic_calibration(
            component, nominal, error, repeats=repeats, group_offsets=group_offsets, measurement_noise=meas,
            reference_noise=ref, positioning_jitter=jitter, rng=rng)
        truth[component], offsets[component] = error, group_offsets
        sigma[component] = float(np.hypot(meas, ref))
    return SyntheticScenario(data, truth, offsets, sigma)


# --- the hard campaigns -----------------------------------------------------------------------

#: Amplitudes of the hard error curve in µm (linear) and arc-seconds (angular): scale, quadratic,
#: cubic, fast ripple, slow ripple, end bends.
HARD_AMPLITUDES = {"linear": (55.0, 18.0, 8.0, 5.0, 1.5, 9.0), "angular": (30.0, 10.0, 5.0, 2.5, 1.0, 4.5)}
HARD_GROUP_OFFSETS = {"linear": (10.0, 40.0), "angular": (5.0, 20.0)}  # µm, ″
HARD_HYSTERESIS = {"linear": (2.0, 4.0), "angular": (0.7, 1.3)}  # full difference, µm, ″

#: Shapes of the hard error curve (``hard_campaign(profile=...)``); the fast ripple's period in grid steps:
#: "hard": every term, the fast ripple's period 3.4–6 steps (never within 0.15 of an integer);
#: "short-ripple": every term, the fast ripple's period 3.0–3.4 steps (encoder or gear ripple a
#:     few calibration steps long, beside the slower terms);
#: "ripple-alone": the scale error and the fast ripple only (period 3.0–6.0 steps);
#: "harmonics": every term, the fast ripple replaced by an eccentricity-like pair: a fundamental of
#:     6.0–6.8 steps and its second harmonic (3.0–3.4 steps), 0.5–1× the fundamental's amplitude.
HARD_PROFILES = ("hard", "short-ripple", "ripple-alone", "harmonics")
_FAST_PERIODS = {"short-ripple": (3.0, 3.4), "ripple-alone": (3.0, 6.0), "harmonics": (3.0, 3.4)}
#: The other profiles' fast ripple: up to 5 µm / 4″ (drawn 0.6–1×), 8–12× an observation's noise, as
#: encoder eccentricity and gear ripple of a robot axis can be.
SHORT_RIPPLE_AMPLITUDES = {"linear": 5.0, "angular": 4.0}


def _non_integer(rng: np.random.Generator, lo: float, hi: float) -> float:
    """A number in [lo, hi] at least 0.15 away from every integer."""
    while True:
        value = rng.uniform(lo, hi)
        if abs(value - round(value)) > 0.15:
            return float(value)


def _hard_error(rng: np.random.Generator, nominal: np.ndarray, unit: float, angular: bool, profile: str = "hard",
                ripple_period: float | None = None, extra: np.random.Generator | None = None) -> ErrorFunction:
    """The hard error curve. ``rng`` draws exactly what the "hard" profile needs (so every profile's
    campaign shares the hard one's noise and offsets); what another profile changes comes from
    ``extra``. ``ripple_period`` (grid steps) fixes the fastest ripple's period."""
    lo, hi = float(nominal[0]), float(nominal[-1])
    step, mid, half = float(nominal[1] - nominal[0]), 0.5 * (lo + hi), 0.5 * (hi - lo)
    amplitudes = HARD_AMPLITUDES["angular" if angular else "linear"]
    scale, quadratic, cubic, ripple, slow, bend = (a * unit for a in amplitudes)
    sign = lambda: rng.choice([-1.0, 1.0])
    a1, a2, a3 = (sign() * rng.uniform(lo_, 1.0) * a for lo_, a in ((0.7, scale), (0.5, quadratic), (0.5, cubic)))
    r1, p1, ph1 = rng.uniform(0.6, 1.0) * ripple, _non_integer(rng, 3.4, 6.0) * step, rng.uniform(0, 2 * np.pi)
    r2, p2, ph2 = rng.uniform(0.6, 1.0) * slow, _non_integer(rng, 8.0, 14.0) * step, rng.uniform(0, 2 * np.pi)
    b0, l0 = sign() * rng.uniform(0.5, 1.0) * bend, rng.uniform(1.3, 3.0) * step
    b1, l1 = sign() * rng.uniform(0.5, 1.0) * bend, rng.uniform(1.3, 3.0) * step
    r3, p3, ph3 = 0.0, 1.0, 0.0  # the harmonics profile's fundamental
    if profile != "hard" or ripple_period is not None:
        extra = extra if extra is not None else rng
        fast = ripple_period if ripple_period is not None else extra.uniform(*_FAST_PERIODS.get(profile, (3.4, 6.0)))
        p1 = fast * step
        r1 *= SHORT_RIPPLE_AMPLITUDES["angular" if angular else "linear"] / amplitudes[3]
        if profile == "ripple-alone":
            a2 = a3 = r2 = b0 = b1 = 0.0
        if profile == "harmonics":
            r3, p3, ph3 = r1, 2.0 * p1, extra.uniform(0, 2 * np.pi)
            r1 = extra.uniform(0.5, 1.0) * r3

    def error(v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, dtype=float)
        u = (v - mid) / half
        return (a1 * u + a2 * (u**2 - 1.0 / 3.0) + a3 * (u**3 - 0.6 * u)
                + r1 * np.sin(2 * np.pi * (v - lo) / p1 + ph1) + r2 * np.sin(2 * np.pi * (v - lo) / p2 + ph2)
                + r3 * np.sin(2 * np.pi * (v - lo) / p3 + ph3)
                + b0 * np.exp(-(v - lo) / l0) + b1 * np.exp(-(hi - v) / l1))

    return error


@dataclass(frozen=True)
class HeldOutSet:
    """Observations a calibration never saw, with the oracle's prediction of their error.

    Attributes
    ----------
    kind : str
        ``"off-grid"`` (random positions between the calibration points, in the calibration's own
        sessions: the model's group offsets apply) or ``"new-session"`` (a start pose outside the
        calibration: the session's offset is unknowable, so both model and oracle are scored with
        the session's mean residual removed).
    measured, reference : (m,) arrays
    group : (m,) int array
        Calibration group of each observation (−1, −2, … for the new session's start poses).
    direction : (m,) array of ±1, or None
    oracle_error : (m,) array
        The error an oracle that knows the true curve, offsets and hysteresis predicts from the
        measured value alone.
    """

    kind: str
    measured: np.ndarray
    reference: np.ndarray
    group: np.ndarray
    direction: np.ndarray | None
    oracle_error: np.ndarray

    @property
    def error(self) -> np.ndarray:
        return self.measured - self.reference

    @property
    def offset_known(self) -> bool:
        return self.kind == "off-grid"


@dataclass(frozen=True)
class Campaign:
    """One hard calibration campaign of one component with its truth and held-out sets.

    Attributes
    ----------
    calibration : CalibrationData
    held_out : tuple of HeldOutSet (off-grid, new-session)
    true_error : callable(true value, direction) → error of group 0 (direction 0 = mid-way)
    group_offsets : (n_groups,) array
    noise_sigma : float
        Standard deviation of one observation's error noise.
    hysteresis : bool
    """

    calibration: CalibrationData
    held_out: tuple[HeldOutSet, ...]
    true_error: Callable[[np.ndarray, np.ndarray | int], np.ndarray]
    group_offsets: np.ndarray
    noise_sigma: float
    hysteresis: bool


def hard_campaign(seed: int, component: str, *, hysteresis: bool = False, bidirectional: bool | None = None,
                  profile: str = "hard", ripple_period: float | None = None, n_points: int = 15, repeats: int = 3,
                  n_groups: int = 3, n_off_grid: int = 20, n_new_session: int = 45, n_new_groups: int = 1
                  ) -> Campaign:
    """A calibration campaign harder than the paper-like one, with held-out data and an oracle.

    Parameters
    ----------
    seed : int
        Campaign seed; the component is mixed into the random stream.
    component : str
    hysteresis : bool
        Give the error a direction-dependent part (full difference 2–4 µm / 0.7–1.3″, sloping by
        up to ±30 % over the range).
    bidirectional : bool, optional
        Calibrate from both directions (``repeats`` approaches from each); default: when
        ``hysteresis``. A one-directional calibration of a hysteretic component approaches from
        +1 only and records it; one without hysteresis records no direction.
    profile : str
        Shape of the error curve, one of ``HARD_PROFILES``. Every profile of one (seed, component)
        shares the "hard" campaign's noise, offsets and held-out positions; only the curve differs.
    ripple_period : float, optional
        The fastest ripple's period in grid steps (default: drawn from the profile's range).
    n_points, repeats, n_groups : int
        The paper's 15 × 3 × 3 by default.
    n_off_grid : int
        Held-out off-grid observations per calibration group.
    n_new_session : int
        Observations of the new session, split evenly between its groups.
    n_new_groups : int
        Start poses of the new session, each with its own offset beyond every calibration
        group's (labelled −1, −2, …; each scored with its own mean residual removed).

    Returns
    -------
    Campaign
    """
    check_component(component)
    if profile not in HARD_PROFILES:
        raise ValueError(f"profile must be one of {HARD_PROFILES}, got {profile!r}")
    rng = np.random.default_rng([seed, COMPONENTS.index(component), 9283])
    extra = np.random.default_rng([seed, COMPONENTS.index(component), 9283, HARD_PROFILES.index(profile)])
    angular = component not in LINEAR_COMPONENTS
    nominal, unit, meas_noise, ref_noise, jitter = _design(component, n_points)
    lo, hi, step = float(nominal[0]), float(nominal[-1]), float(nominal[1] - nominal[0])
    curve = _hard_error(rng, nominal, unit, angular, profile, ripple_period, extra)
    kind = "angular" if angular else "linear"
    h0 = rng.uniform(*HARD_HYSTERESIS[kind]) * unit if hysteresis else 0.0
    h1 = rng.uniform(-0.3, 0.3) * h0

    def hysteresis_curve(v: np.ndarray) -> np.ndarray:
        return h0 + h1 * (np.asarray(v, float) - 0.5 * (lo + hi)) / (0.5 * (hi - lo))

    offset_lo, offset_hi = HARD_GROUP_OFFSETS[kind]
    offsets = np.concatenate([[0.0], rng.choice([-1.0, 1.0], n_groups - 1)
                              * rng.uniform(offset_lo, offset_hi, n_groups - 1) * unit])
    bidirectional = hysteresis if bidirectional is None else bidirectional
    directions = (-1, 1) if bidirectional else ((1,) if hysteresis else None)
    calibration = synthetic_calibration(
        component, nominal, curve, repeats=repeats, group_offsets=offsets, measurement_noise=meas_noise,
        reference_noise=ref_noise, positioning_jitter=jitter, hysteresis=hysteresis_curve if hysteresis else None,
        directions=directions, rng=rng)

    def true_error(v: np.ndarray, direction: np.ndarray | int = 0) -> np.ndarray:
        return curve(v) + np.asarray(direction) * hysteresis_curve(v) / 2.0

    def observe(kind_: str, true_value: np.ndarray, group: np.ndarray, offset: np.ndarray) -> HeldOutSet:
        moving = hysteresis or bidirectional
        direction = rng.choice([-1, 1], true_value.size) if moving else None
        d = np.zeros(true_value.size) if direction is None else direction
        reference = true_value + rng.normal(0.0, ref_noise, true_value.size)
        measured = true_value + true_error(true_value, d) + offset + rng.normal(0.0, meas_noise, true_value.size)
        # the oracle inverts measured = t + e(t) + offset for t (|e'| ≪ 1: a contraction)
        t = measured.copy()
        for _ in range(30):
            t = measured - true_error(t, d) - offset
        return HeldOutSet(kind_, measured, reference, group, direction, true_error(t, d) + offset)

    inner = (lo + 0.05 * step, hi - 0.05 * step)
    group = np.repeat(np.arange(n_groups), n_off_grid)
    off_grid = observe("off-grid", rng.uniform(*inner, group.size), group, offsets[group])
    session_offset = rng.choice([-1.0, 1.0]) * rng.uniform(offset_hi, 1.5 * offset_hi) * unit
    per_group = n_new_session // max(n_new_groups, 1)
    positions, labels, session_offsets = [rng.uniform(*inner, per_group)], [np.full(per_group, -1)], [session_offset]
    for k in range(2, n_new_groups + 1):  # drawn after the first, so one new group leaves the stream unchanged
        positions.append(rng.uniform(*inner, per_group))
        labels.append(np.full(per_group, -k))
        session_offsets.append(rng.choice([-1.0, 1.0]) * rng.uniform(offset_hi, 1.5 * offset_hi) * unit)
    new_labels = np.concatenate(labels)
    new_session = observe("new-session", np.concatenate(positions), new_labels,
                          np.repeat(np.array(session_offsets), per_group))
    return Campaign(calibration, (off_grid, new_session), true_error, offsets, float(np.hypot(meas_noise, ref_noise)),
                    hysteresis)


class ErrorModel(Protocol):
    def predict(self, measured: np.ndarray, direction: np.ndarray | None = None) -> np.ndarray: ...

    def group_offset(self, group: int) -> float: ...


def held_out_residuals(model: ErrorModel, held: HeldOutSet) -> tuple[np.ndarray, np.ndarray]:
    """Residuals of a fitted model and of the oracle on a held-out set (SI).

    Off-grid observations are predicted in their calibration group's frame (the model's own
    offset for that group); for the new session both residuals have each start pose's mean
    removed, since neither the model nor the oracle can know a new start pose's offset.

    Parameters
    ----------
    model : a FittedModel (anything with ``predict(measured, direction)`` and ``group_offset(g)``)
    held : HeldOutSet

    Returns
    -------
    model_residual, oracle_residual : (m,) arrays, observed error minus prediction
    """
    predicted = np.asarray(model.predict(held.measured, held.direction), dtype=float)
    if held.offset_known:
        predicted = predicted - np.array([model.group_offset(int(g)) for g in held.group])
    residual, oracle = held.error - predicted, held.error - held.oracle_error
    if not held.offset_known:
        for g in np.unique(held.group):
            at = held.group == g
            residual[at] -= residual[at].mean()
            oracle[at] -= oracle[at].mean()
    return residual, oracle
