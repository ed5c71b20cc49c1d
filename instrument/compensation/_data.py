"""Calibration data: the container, repeat statistics, and a paper-like synthetic scenario."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

#: Pose components: x, y, z in metres; a, b, c (ISO 9283 = the paper's α, θ, γ) in radians.
COMPONENTS = ("x", "y", "z", "a", "b", "c")
LINEAR_COMPONENTS = ("x", "y", "z")
ANGULAR_COMPONENTS = ("a", "b", "c")

ARCSEC = np.pi / (180.0 * 3600.0)  # one arc-second in radians
MICROMETRE = 1e-6


def display_unit(component: str) -> tuple[str, float]:
    """Report unit and the factor SI value × factor = displayed value (µm or arc-seconds)."""
    if component in LINEAR_COMPONENTS:
        return "um", 1.0 / MICROMETRE
    if component in ANGULAR_COMPONENTS:
        return "arcsec", 1.0 / ARCSEC
    raise ValueError(f"unknown pose component {component!r}; expected one of {COMPONENTS}")


def check_component(component: str) -> str:
    if component not in COMPONENTS:
        raise ValueError(f"unknown pose component {component!r}; expected one of {COMPONENTS}")
    return component


@dataclass(frozen=True)
class CalibrationData:
    """Calibration observations of one pose component against a reference instrument.

    One row per observation (one repeat at one calibration point in one group).

    Attributes
    ----------
    component : str
        One of ``COMPONENTS``.
    measured : (n,) array
        Value reported by the instrument (m or rad).
    reference : (n,) array
        Value given by the reference instrument (interferometer, rotary table, theodolite).
    group : (n,) int array
        Calibration group (each started from a different initial pose; paper §3.4 step 1).
    point : (n,) int array
        Calibration point index (the commanded position); repeats share it across groups.
    """

    component: str
    measured: np.ndarray
    reference: np.ndarray
    group: np.ndarray
    point: np.ndarray

    def __post_init__(self) -> None:
        check_component(self.component)
        measured = np.asarray(self.measured, dtype=float).ravel()
        reference = np.asarray(self.reference, dtype=float).ravel()
        group = np.asarray(self.group).ravel()
        point = np.asarray(self.point).ravel()
        n = measured.size
        if not (reference.size == group.size == point.size == n):
            raise ValueError(
                f"CalibrationData({self.component}): measured, reference, group, point must have one "
                f"length; got {n}, {reference.size}, {group.size}, {point.size}"
            )
        if n == 0 or not (np.all(np.isfinite(measured)) and np.all(np.isfinite(reference))):
            raise ValueError(f"CalibrationData({self.component}): values must be finite and non-empty")
        object.__setattr__(self, "measured", measured)
        object.__setattr__(self, "reference", reference)
        object.__setattr__(self, "group", group.astype(int))
        object.__setattr__(self, "point", point.astype(int))

    @property
    def error(self) -> np.ndarray:
        """Measurement error, measured − reference."""
        return self.measured - self.reference

    def subset(self, mask: np.ndarray) -> CalibrationData:
        return CalibrationData(
            self.component, self.measured[mask], self.reference[mask], self.group[mask], self.point[mask]
        )


def point_means(measured: np.ndarray, error: np.ndarray, point: np.ndarray):
    """Average all observations of each calibration point.

    Returns
    -------
    x_mean, e_mean, count, labels : arrays sorted by x_mean.
    """
    labels, inverse, count = np.unique(point, return_inverse=True, return_counts=True)
    x_mean = np.bincount(inverse, weights=measured) / count
    e_mean = np.bincount(inverse, weights=error) / count
    order = np.argsort(x_mean)
    return x_mean[order], e_mean[order], count[order].astype(float), labels[order]


def infer_points(measured: np.ndarray, gap_fraction: float = 0.25) -> np.ndarray:
    """Label calibration points by clustering sorted measured values.

    A new point starts where the gap to the previous value exceeds ``gap_fraction`` of the
    largest gap (repeats sit far closer together than the calibration step).
    """
    measured = np.asarray(measured, dtype=float)
    order = np.argsort(measured)
    gaps = np.diff(measured[order])
    if gaps.size == 0 or gaps.max() <= 0:
        return np.zeros(measured.size, dtype=int)
    starts = np.concatenate([[0], np.cumsum(gaps > gap_fraction * gaps.max())])
    labels = np.empty(measured.size, dtype=int)
    labels[order] = starts
    return labels


def noise_floor(measured_error: np.ndarray, group: np.ndarray, point: np.ndarray) -> float:
    """Pooled repeat scatter (standard deviation, ddof = 1 per cell) of the error.

    Cells are (group, point); this is the scatter of one observation that no model of the error
    curve can remove (instrument noise plus reference noise).
    """
    keys = np.stack([np.asarray(group), np.asarray(point)], axis=1)
    _, inverse, count = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    means = np.bincount(inverse, weights=measured_error) / count
    ss = np.sum((measured_error - means[inverse]) ** 2)
    dof = np.sum(count - 1)
    if dof <= 0:
        raise ValueError("noise floor needs repeated observations at some calibration point")
    return float(np.sqrt(ss / dof))


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

    data: dict
    true_error: dict
    group_offsets: dict
    noise_sigma: dict = field(default_factory=dict)


def synthetic_calibration(
    component: str,
    nominal: np.ndarray,
    error_function: Callable[[np.ndarray], np.ndarray],
    *,
    repeats: int = 3,
    group_offsets=(0.0,),
    measurement_noise: float,
    reference_noise: float,
    positioning_jitter: float = 0.0,
    rng: np.random.Generator,
) -> CalibrationData:
    """Simulate one calibration: every group visits every nominal point ``repeats`` times.

    The stage stops at nominal + jitter (the true value); the reference reads true + its noise;
    the instrument reads true + error(true) + group offset + its noise.
    """
    nominal = np.asarray(nominal, dtype=float)
    n_groups = len(group_offsets)
    g, p, _ = np.meshgrid(np.arange(n_groups), np.arange(nominal.size), np.arange(repeats), indexing="ij")
    g, p = g.ravel(), p.ravel()
    true_value = nominal[p] + rng.normal(0.0, positioning_jitter, p.size) if positioning_jitter else nominal[p]
    reference = true_value + rng.normal(0.0, reference_noise, p.size)
    measured = (
        true_value
        + error_function(true_value)
        + np.asarray(group_offsets, dtype=float)[g]
        + rng.normal(0.0, measurement_noise, p.size)
    )
    return CalibrationData(component, measured, reference, g, p)


def _paper_like_error(rng: np.random.Generator, lo: float, hi: float, unit: float, amplitudes):
    """A smooth error curve: scale error + quadratic + one periodic term (amplitudes in ``unit``)."""
    linear, quadratic, periodic = amplitudes
    a1 = rng.choice([-1.0, 1.0]) * rng.uniform(0.75, 1.0) * linear * unit
    a2 = rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 1.0) * quadratic * unit
    a3 = rng.uniform(0.5, 1.0) * periodic * unit
    period = rng.uniform(0.45, 0.7) * (hi - lo)
    phase = rng.uniform(0.0, 2 * np.pi)
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)

    def error(v):
        u = (np.asarray(v, dtype=float) - mid) / half
        return a1 * u + a2 * (u**2 - 1.0 / 3.0) + a3 * np.sin(2 * np.pi * (v - lo) / period + phase)

    return error


def paper_like_scenario(seed: int = 0, *, n_points: int = 15, repeats: int = 3, n_groups: int = 3) -> SyntheticScenario:
    """The paper's calibration design (§3.4 step 1, §4.2) with a known, smooth error.

    - x, y, z: 15 points 0–70 mm in 5 mm steps; error scale + quadratic + periodic, up to about
      ±80 µm; instrument noise 0.4 µm, interferometer noise 0.1 µm (1σ); stage positioning
      jitter 3 µm; group offsets 3–8 µm (group 0 has none). The periodic term's period is
      0.45–0.7 of the range (about 6–10 calibration steps): structure finer than two steps cannot
      be checked by any held-out scheme, since leaving a point out doubles the local step.
    - a, b, c: 15 points −1.75° … +1.75° in 0.25° steps (the paper calibrates small rotations on a
      rotary table; it does not print the range); error up to about ±40″; instrument noise 0.4″,
      table noise 0.3″; jitter 1″; group offsets 2–5″.
    """
    rng = np.random.default_rng(seed)
    data, truth, offsets, sigma = {}, {}, {}, {}
    for component in COMPONENTS:
        if component in LINEAR_COMPONENTS:
            nominal = np.linspace(0.0, 0.070, n_points)
            unit, amplitudes = MICROMETRE, (55.0, 18.0, 6.0)
            meas, ref, jitter, offset_range = 0.4 * unit, 0.1 * unit, 3.0 * unit, (3.0, 8.0)
        else:
            nominal = np.deg2rad(np.linspace(-1.75, 1.75, n_points))
            unit, amplitudes = ARCSEC, (28.0, 9.0, 3.0)
            meas, ref, jitter, offset_range = 0.4 * unit, 0.3 * unit, 1.0 * unit, (2.0, 5.0)
        error = _paper_like_error(rng, nominal[0], nominal[-1], unit, amplitudes)
        group_offsets = np.concatenate(
            [[0.0], rng.choice([-1.0, 1.0], n_groups - 1) * rng.uniform(*offset_range, n_groups - 1) * unit]
        )
        data[component] = synthetic_calibration(
            component,
            nominal,
            error,
            repeats=repeats,
            group_offsets=group_offsets,
            measurement_noise=meas,
            reference_noise=ref,
            positioning_jitter=jitter,
            rng=rng,
        )
        truth[component], offsets[component] = error, group_offsets
        sigma[component] = float(np.hypot(meas, ref))
    return SyntheticScenario(data, truth, offsets, sigma)


def as_data_mapping(calibration_data) -> Mapping[str, CalibrationData]:
    """Accept one CalibrationData, a sequence of them, or a mapping component → CalibrationData."""
    if isinstance(calibration_data, CalibrationData):
        return {calibration_data.component: calibration_data}
    if isinstance(calibration_data, Mapping):
        return dict(calibration_data)
    return {d.component: d for d in calibration_data}
