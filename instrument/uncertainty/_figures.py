"""The ISO 9283 figures the Monte Carlo propagates, computed by ``instrument.iso9283`` itself.

An evaluator maps the tool poses of its pose sets to named figure values. Each figure has a
unit, a kind (signed; non-negative, whose bias-corrected value is clipped at 0; or absolute: the
drift |first − last|, propagated as the signed difference and reported as its magnitude, so that
U of the difference also covers the magnitude: ||a| − |b|| ≤ |a − b|), and, where
``instrument.iso9283`` computes one, its sampling confidence interval.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from instrument.iso9283 import (
    distance_characteristics,
    multidirectional_variation,
    pose_accuracy,
    pose_drift,
    pose_repeatability,
    wrap_angle,
)


class Kind(StrEnum):
    SIGNED = "signed"
    NON_NEGATIVE = "non-negative"
    ABSOLUTE = "absolute"


LENGTH_FIGURES = {"rp_l", "ap_p", "ap_x", "ap_y", "ap_z", "dap_p", "drp_l", "ad_p", "ad_x", "ad_y", "ad_z",
                  "rd_p", "rd_x", "rd_y", "rd_z", "vap_p"}
REPEATABILITY = ("rp_l", "rp_a", "rp_b", "rp_c")
ACCURACY = ("ap_p", "ap_x", "ap_y", "ap_z", "ap_a", "ap_b", "ap_c")
DRIFT = ("dap_p", "dap_a", "dap_b", "dap_c", "drp_l", "drp_a", "drp_b", "drp_c")
DISTANCE = ("ad_p", "ad_x", "ad_y", "ad_z", "ad_a", "ad_b", "ad_c", "rd_p", "rd_x", "rd_y", "rd_z", "rd_a", "rd_b",
            "rd_c")
DIRECTIONS = ("vap_p", "vap_a", "vap_b", "vap_c")
SIGNED_FIGURES = {"ap_x", "ap_y", "ap_z", "ap_a", "ap_b", "ap_c", "ad_p", "ad_x", "ad_y", "ad_z", "ad_a", "ad_b",
                  "ad_c"}


def unit_of(name: str) -> str:
    return "m" if name in LENGTH_FIGURES else "rad"


def kind_of(name: str) -> Kind:
    if name in DRIFT:
        return Kind.ABSOLUTE
    return Kind.SIGNED if name in SIGNED_FIGURES else Kind.NON_NEGATIVE


Poses = Mapping[str, np.ndarray]
Interval = tuple[float, float]


@dataclass(frozen=True)
class Evaluator:
    """Figures of one owner (a point, a pair of points, a point's approach directions)."""

    group: str  # "points", "distances", "directions"
    owner: str  # "P1", "P2-P4", ...
    names: tuple[str, ...]
    compute: Callable[[Poses], dict[str, float]]
    intervals: Callable[[Poses, float], dict[str, Interval]] | None = None


def point_evaluator(label: str, commanded: np.ndarray) -> Evaluator:
    def compute(poses: Poses) -> dict[str, float]:
        rp = pose_repeatability(poses[label])
        ap = pose_accuracy(poses[label], commanded)
        return {name: float(getattr(rp, name)) for name in REPEATABILITY} | {
            name: float(getattr(ap, name)) for name in ACCURACY}

    def intervals(poses: Poses, confidence: float) -> dict[str, Interval]:
        if len(poses[label]) < 3:
            return {}
        rp = pose_repeatability(poses[label], confidence=confidence)
        ap = pose_accuracy(poses[label], commanded, confidence=confidence)
        found = {f"{n}_ci": getattr(rp, f"{n}_ci", None) for n in REPEATABILITY}
        found |= {f"{n}_ci": getattr(ap, f"{n}_ci", None) for n in ACCURACY}
        return {key[:-3]: (float(v[0]), float(v[1])) for key, v in found.items() if v is not None}

    return Evaluator("points", label, REPEATABILITY + ACCURACY, compute, intervals)


def drift_evaluator(label: str, commanded: np.ndarray, cycles: int) -> Evaluator:
    """Signed first − last differences of AP and RP over the first and last ``cycles`` cycles."""

    def compute(poses: Poses) -> dict[str, float]:
        drift = pose_drift(poses[label][:cycles], poses[label][-cycles:], commanded)
        (ap1, rp1), (ap2, rp2) = drift.first, drift.last
        out = {"dap_p": ap1.ap_p - ap2.ap_p, "drp_l": rp1.rp_l - rp2.rp_l}
        for axis in "abc":
            out[f"dap_{axis}"] = float(wrap_angle(getattr(ap1, f"ap_{axis}") - getattr(ap2, f"ap_{axis}")))
            out[f"drp_{axis}"] = getattr(rp1, f"rp_{axis}") - getattr(rp2, f"rp_{axis}")
        return {name: float(out[name]) for name in DRIFT}

    return Evaluator("points", label, DRIFT, compute)


def distance_evaluator(first: str, second: str, commanded_1: np.ndarray, commanded_2: np.ndarray) -> Evaluator:
    def compute(poses: Poses) -> dict[str, float]:
        result = distance_characteristics(poses[first], poses[second], commanded_1, commanded_2)
        return {name: float(getattr(result, name)) for name in DISTANCE}

    return Evaluator("distances", f"{first}-{second}", DISTANCE, compute)


def direction_evaluator(point: str, labels: tuple[str, ...]) -> Evaluator:
    def compute(poses: Poses) -> dict[str, float]:
        result = multidirectional_variation([poses[label] for label in labels])
        return {name: float(getattr(result, name)) for name in DIRECTIONS}

    return Evaluator("directions", point, DIRECTIONS, compute)
