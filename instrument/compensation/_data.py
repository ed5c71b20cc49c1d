"""Calibration data: the container, its one input convention, and repeat statistics.

A calibration observation is (measured, reference) of one pose component, with the calibration
group (start pose), the calibration point (commanded position) and optionally the approach
direction (+1 from below, −1 from above). The error is always derived inside as
measured − reference; nothing in this package takes an error array from the caller.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from instrument._conventions import ARCSEC, COMPONENTS

#: Pose components: x, y, z in metres; a, b, c (ISO 9283 = the paper's α, θ, γ) in radians.
LINEAR_COMPONENTS = ("x", "y", "z")
ANGULAR_COMPONENTS = ("a", "b", "c")

MICROMETRE = 1e-6

#: Largest plausible ratio of the error's spread to the measured range. A real calibration error is
#: a few per cent of the range at most; an error passed as the reference (or the other way round)
#: makes the derived "error" span the whole range (ratio ≈ 1).
MAX_ERROR_TO_RANGE = 0.25


class InsufficientCalibrationData(ValueError):
    """Calibration data that cannot support a fit or its held-out evaluation (too few points, no
    repeats): the message is one line naming the component and what is missing."""


def display_unit(component: str) -> tuple[str, float]:
    """Display unit of a component's errors.

    Parameters
    ----------
    component : str
        One of ``COMPONENTS``.

    Returns
    -------
    unit, factor : str, float
        ``"um"`` or ``"arcsec"``, and the factor with SI value × factor = displayed value.
    """
    if component in LINEAR_COMPONENTS:
        return "um", 1.0 / MICROMETRE
    if component in ANGULAR_COMPONENTS:
        return "arcsec", 1.0 / ARCSEC
    raise ValueError(f"unknown pose component {component!r}; expected one of {COMPONENTS}")


def check_component(component: str) -> str:
    if component not in COMPONENTS:
        raise ValueError(f"unknown pose component {component!r}; expected one of {COMPONENTS}")
    return component


def check_direction(direction: object, where: str) -> np.ndarray | None:
    """``None`` or an int array of ±1 (a scalar broadcasts later)."""
    if direction is None:
        return None
    d = np.asarray(direction)
    if d.dtype == object or not np.all(np.isin(d, (-1, 1))):
        raise ValueError(f"{where}: approach direction must be +1, -1 or None, got {direction!r}")
    return d.astype(int)


@dataclass(frozen=True)
class CalibrationData:
    """Calibration observations of one pose component against a reference instrument.

    One row per observation (one approach to one calibration point in one group).

    Attributes
    ----------
    component : str
        One of ``COMPONENTS``.
    measured : (n,) array
        Value reported by the instrument (m or rad).
    reference : (n,) array
        Value given by the reference instrument (interferometer, rotary table, theodolite) for the
        same pose. Never the error: the error is ``measured − reference``, derived here, and data
        whose derived error spans more than ``MAX_ERROR_TO_RANGE`` of the measured range is
        refused (that is what passing the error as the reference looks like).
    group : (n,) int array, optional
        Calibration group (each started from a different initial pose; paper §3.4 step 1).
        Default (None or empty): one group.
    point : (n,) int array, optional
        Calibration point (the commanded position); repeats share it across groups and
        directions. Default (None or empty): inferred by clustering the measured values (``infer_points``).
    direction : (n,) array of ±1, optional
        Approach direction of each observation (+1: the point was approached from below, −1:
        from above), as in a bidirectional calibration (ISO 230-2). ``None``: not recorded
        (a one-directional calibration whose direction is unknown).
    """

    component: str
    measured: np.ndarray
    reference: np.ndarray
    group: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    point: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    direction: np.ndarray | None = None

    def __post_init__(self) -> None:
        where = f"CalibrationData({self.component})"
        check_component(self.component)
        measured = np.asarray(self.measured, dtype=float).ravel()
        reference = np.asarray(self.reference, dtype=float).ravel()
        n = measured.size
        given = lambda labels: labels is not None and np.size(labels) > 0  # None or empty: not given
        group = np.asarray(self.group).ravel() if given(self.group) else np.zeros(n, int)
        if n == 0 or not (np.all(np.isfinite(measured)) and np.all(np.isfinite(reference))):
            raise ValueError(f"{where}: measured and reference must be finite and non-empty")
        point = np.asarray(self.point).ravel() if given(self.point) else infer_points(measured)
        direction = check_direction(self.direction, where)
        sizes = [reference.size, group.size, point.size] + ([] if direction is None else [direction.size])
        if any(s != n for s in sizes):
            raise ValueError(f"{where}: measured, reference, group, point (and direction) must have one length; "
                             f"got {n}, {', '.join(str(s) for s in sizes)}")
        error_spread, measured_range = float(np.ptp(measured - reference)), float(np.ptp(measured))
        if measured_range > 0 and error_spread > MAX_ERROR_TO_RANGE * measured_range:
            raise ValueError(
                f"{where}: the error measured − reference spans {error_spread:.6g} over a measured range of "
                f"{measured_range:.6g}; pass the reference instrument's reading as 'reference', not the error")
        object.__setattr__(self, "measured", measured)
        object.__setattr__(self, "reference", reference)
        object.__setattr__(self, "group", group.astype(int))
        object.__setattr__(self, "point", point.astype(int))
        object.__setattr__(self, "direction", direction)

    @property
    def error(self) -> np.ndarray:
        """Measurement error, measured − reference."""
        return self.measured - self.reference

    @property
    def directions(self) -> tuple[int, ...]:
        """Approach directions present: ``()`` when not recorded, ``(1,)``, ``(-1,)`` or ``(-1, 1)``."""
        return () if self.direction is None else tuple(int(d) for d in np.unique(self.direction))

    @property
    def bidirectional(self) -> bool:
        return len(self.directions) == 2

    @property
    def n_points(self) -> int:
        return int(np.unique(self.point).size)

    def subset(self, mask: np.ndarray) -> CalibrationData:
        """The observations selected by a boolean mask (or index array)."""
        return CalibrationData(self.component, self.measured[mask], self.reference[mask], self.group[mask],
                               self.point[mask], None if self.direction is None else self.direction[mask])

    def point_order(self) -> np.ndarray:
        """Point labels sorted by their mean measured value."""
        labels = np.unique(self.point)
        centers = np.array([self.measured[self.point == p].mean() for p in labels])
        return labels[np.argsort(centers)]

    def summary(self) -> dict:
        """What the data is, for the record: counts, directions, range, and a SHA-256 of the arrays."""
        import hashlib

        digest = hashlib.sha256()
        for array in (self.measured, self.reference, self.group, self.point,
                      np.zeros(0) if self.direction is None else self.direction):
            digest.update(np.ascontiguousarray(array).tobytes())
        return {
            "n_observations": int(self.measured.size),
            "n_points": self.n_points,
            "n_groups": int(np.unique(self.group).size),
            "directions": list(self.directions),
            "measured_range": [float(self.measured.min()), float(self.measured.max())],
            "data_sha256": digest.hexdigest(),
        }


def point_means(measured: np.ndarray, error: np.ndarray, point: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Average all observations of each calibration point.

    Parameters
    ----------
    measured, error, point : (n,) arrays
        Observations and their point labels.

    Returns
    -------
    x_mean, e_mean, count, labels : arrays
        Per point, sorted by ``x_mean``.
    """
    labels, inverse, count = np.unique(point, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    x_mean = np.bincount(inverse, weights=measured) / count
    e_mean = np.bincount(inverse, weights=error) / count
    order = np.argsort(x_mean)
    return x_mean[order], e_mean[order], count[order].astype(float), labels[order]


def infer_points(measured: np.ndarray, gap_fraction: float = 0.25) -> np.ndarray:
    """Label calibration points by clustering sorted measured values.

    A new point starts where the gap to the previous value exceeds ``gap_fraction`` of the
    largest gap (repeats sit far closer together than the calibration step).

    Parameters
    ----------
    measured : (n,) array
    gap_fraction : float

    Returns
    -------
    (n,) int array of point labels, numbered in increasing measured value.
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


def noise_floor(error: np.ndarray, *labels: np.ndarray) -> float:
    """Pooled repeat scatter (standard deviation, ddof = 1 per cell) of the error.

    Parameters
    ----------
    error : (n,) array
    *labels : (n,) arrays
        Cell labels, e.g. group, point and direction: a cell holds the repeats of one point.

    Returns
    -------
    float
        The scatter of one observation that no model of the error curve can remove (instrument
        noise plus reference noise).
    """
    keys = np.stack([np.asarray(label) for label in labels], axis=1)
    _, inverse, count = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    means = np.bincount(inverse, weights=error) / count
    ss = np.sum((error - means[inverse]) ** 2)
    dof = np.sum(count - 1)
    if dof <= 0:
        raise InsufficientCalibrationData("noise floor needs repeated observations at some calibration point")
    return float(np.sqrt(ss / dof))


def data_noise_floor(data: CalibrationData) -> float:
    """``noise_floor`` of a calibration, cells = (group, point, direction)."""
    direction = np.zeros(data.measured.size, int) if data.direction is None else data.direction
    return noise_floor(data.error, data.group, data.point, direction)


def as_data_mapping(calibration_data: CalibrationData | Mapping[str, CalibrationData] | Iterable[CalibrationData]
                    ) -> dict[str, CalibrationData]:
    """Accept one CalibrationData, a sequence of them, or a mapping component → CalibrationData."""
    if isinstance(calibration_data, CalibrationData):
        return {calibration_data.component: calibration_data}
    if isinstance(calibration_data, Mapping):
        return dict(calibration_data)
    return {d.component: d for d in calibration_data}
