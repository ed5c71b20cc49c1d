"""ISO 9283 pose characteristics (method.md §5): RP, AP, AD/RD, vAP, drift.

Input poses are (n, 6) arrays [x, y, z, a, b, c] in metres and radians, one row per attained pose
at one commanded pose; (a, b, c) are the Euler angles (α, θ, γ) of R = Rz(γ)·Ry(θ)·Rx(α). Each
angle column is brought onto one branch around its circular mean before any average; accuracy
angles are wrapped into (−π, π].
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from instrument.iso9283._data import as_commanded, as_poses, wrap_angle
from instrument.iso9283._errors import ISO9283Error
from instrument.iso9283._uncertainty import (
    bootstrap_resamples,
    check_confidence,
    chi_square_interval,
    percentile_interval,
    rp_l_interval,
    t_interval,
)

Interval = tuple[float, float]


@dataclass(frozen=True)
class PoseRepeatability:
    """RP_l = l̄ + 3·S_l (m); RP_a, RP_b, RP_c = 3·S (rad, read as ±). CIs only when asked."""

    n: int
    barycentre: np.ndarray
    l_mean: float
    s_l: float
    rp_l: float
    s_a: float
    s_b: float
    s_c: float
    rp_a: float
    rp_b: float
    rp_c: float
    confidence: float | None = None
    rp_l_ci: Interval | None = None
    rp_a_ci: Interval | None = None
    rp_b_ci: Interval | None = None
    rp_c_ci: Interval | None = None


@dataclass(frozen=True)
class PoseAccuracy:
    """AP_P = |barycentre − commanded| (m); AP_x…AP_z (m) and AP_a…AP_c (rad, in (−π, π])."""

    n: int
    barycentre: np.ndarray
    commanded: np.ndarray
    ap_p: float
    ap_x: float
    ap_y: float
    ap_z: float
    ap_a: float
    ap_b: float
    ap_c: float
    confidence: float | None = None
    ap_p_ci: Interval | None = None
    ap_a_ci: Interval | None = None
    ap_b_ci: Interval | None = None
    ap_c_ci: Interval | None = None


@dataclass(frozen=True)
class DistanceCharacteristics:
    """Distance accuracy AD (mean attained − commanded distance) and repeatability RD (= 3·S).

    ``ad_p``/``rd_p`` use the Euclidean distance between the two attained positions; the per-axis
    and per-angle figures use the signed differences pose 1 − pose 2 (angles wrapped).
    """

    n: int
    commanded_distance: float
    mean_distance: float
    ad_p: float
    ad_x: float
    ad_y: float
    ad_z: float
    ad_a: float
    ad_b: float
    ad_c: float
    rd_p: float
    rd_x: float
    rd_y: float
    rd_z: float
    rd_a: float
    rd_b: float
    rd_c: float


@dataclass(frozen=True)
class MultiDirectionalVariation:
    """vAP_P: largest distance between the barycentres reached from different directions (m);
    vAP_a, vAP_b, vAP_c: largest difference of their mean angles (rad)."""

    directions: int
    barycentres: np.ndarray
    vap_p: float
    vap_a: float
    vap_b: float
    vap_c: float


@dataclass(frozen=True)
class PoseDrift:
    """dAP = |AP(first) − AP(last)|, dRP = |RP(first) − RP(last)| (m / rad)."""

    dap_p: float
    dap_a: float
    dap_b: float
    dap_c: float
    drp_l: float
    drp_a: float
    drp_b: float
    drp_c: float
    first: tuple[PoseAccuracy, PoseRepeatability]
    last: tuple[PoseAccuracy, PoseRepeatability]


def _barycentre(array: np.ndarray) -> np.ndarray:
    centre = array.mean(axis=0)
    centre[3:] = wrap_angle(centre[3:])
    return centre


def pose_repeatability(
    poses, *, confidence: float | None = None, bootstrap_samples: int = 2000, seed: int = 0
) -> PoseRepeatability:
    """ISO 9283 pose repeatability RP_l, RP_a, RP_b, RP_c of n attained poses.

    Parameters
    ----------
    poses : (n, 6) array [x, y, z, a, b, c], m and rad, n ≥ 2
    confidence : float, optional
        Also compute confidence intervals at this level (see ``_uncertainty``: chi-square for
        RP_a/b/c, seeded percentile bootstrap for RP_l).
    bootstrap_samples, seed : int
        Bootstrap resamples and the seed of their generator.
    """
    array = as_poses(poses)
    n = len(array)
    positions = array[:, :3]
    distances = np.linalg.norm(positions - positions.mean(axis=0), axis=1)
    l_mean = float(distances.mean())
    s_l = float(distances.std(ddof=1))
    s_angles = array[:, 3:].std(axis=0, ddof=1)
    result: dict[str, Any] = dict(
        n=n,
        barycentre=_barycentre(array),
        l_mean=l_mean,
        s_l=s_l,
        rp_l=l_mean + 3.0 * s_l,
        s_a=float(s_angles[0]),
        s_b=float(s_angles[1]),
        s_c=float(s_angles[2]),
        rp_a=float(3.0 * s_angles[0]),
        rp_b=float(3.0 * s_angles[1]),
        rp_c=float(3.0 * s_angles[2]),
    )
    if confidence is not None:
        confidence = check_confidence(confidence, n)
        result.update(
            confidence=confidence,
            rp_l_ci=rp_l_interval(positions, confidence, bootstrap_samples, seed),
            rp_a_ci=chi_square_interval(result["rp_a"], n, confidence),
            rp_b_ci=chi_square_interval(result["rp_b"], n, confidence),
            rp_c_ci=chi_square_interval(result["rp_c"], n, confidence),
        )
    return PoseRepeatability(**result)


def pose_accuracy(
    poses, commanded, *, confidence: float | None = None, bootstrap_samples: int = 2000, seed: int = 0
) -> PoseAccuracy:
    """ISO 9283 pose accuracy AP_P, AP_a, AP_b, AP_c of n attained poses against the commanded one.

    Parameters
    ----------
    poses : (n, 6) array [x, y, z, a, b, c], m and rad, n ≥ 1 (n ≥ 3 with ``confidence``)
    commanded : (6,) array, the commanded pose in the same frame and convention
    confidence : float, optional
        Also compute intervals: Student's t for AP_a/b/c, seeded percentile bootstrap for AP_P.
    """
    array = as_poses(poses, minimum=1)
    target = as_commanded(commanded)
    n = len(array)
    centre = array.mean(axis=0)
    offsets = centre[:3] - target[:3]
    angle_errors = wrap_angle(centre[3:] - target[3:])
    result: dict[str, Any] = dict(
        n=n,
        barycentre=_barycentre(array),
        commanded=target,
        ap_p=float(np.linalg.norm(offsets)),
        ap_x=float(offsets[0]),
        ap_y=float(offsets[1]),
        ap_z=float(offsets[2]),
        ap_a=float(angle_errors[0]),
        ap_b=float(angle_errors[1]),
        ap_c=float(angle_errors[2]),
    )
    if confidence is not None:
        confidence = check_confidence(confidence, n)
        resampled = bootstrap_resamples(array[:, :3], bootstrap_samples, seed)
        ap_p_samples = np.linalg.norm(resampled.mean(axis=1) - target[:3], axis=1)
        s_angles = array[:, 3:].std(axis=0, ddof=1)
        result.update(
            confidence=confidence,
            ap_p_ci=percentile_interval(ap_p_samples, confidence),
            ap_a_ci=t_interval(float(angle_errors[0]), float(s_angles[0]), n, confidence),
            ap_b_ci=t_interval(float(angle_errors[1]), float(s_angles[1]), n, confidence),
            ap_c_ci=t_interval(float(angle_errors[2]), float(s_angles[2]), n, confidence),
        )
    return PoseAccuracy(**result)


def distance_characteristics(poses_1, poses_2, commanded_1, commanded_2) -> DistanceCharacteristics:
    """ISO 9283 distance accuracy AD and repeatability RD between two commanded poses.

    Parameters
    ----------
    poses_1, poses_2 : (n, 6) arrays, row j of each from the same cycle j, n ≥ 2
    commanded_1, commanded_2 : (6,) commanded poses
    """
    first = as_poses(poses_1, "poses_1")
    second = as_poses(poses_2, "poses_2")
    if first.shape != second.shape:
        raise ISO9283Error(f"poses_1 and poses_2 must pair up cycle by cycle, got {len(first)} and {len(second)} poses")
    c1, c2 = as_commanded(commanded_1, "commanded_1"), as_commanded(commanded_2, "commanded_2")
    differences = first - second
    differences[:, 3:] = wrap_angle(differences[:, 3:])
    commanded_difference = c1 - c2
    commanded_difference[3:] = wrap_angle(commanded_difference[3:])
    distances = np.linalg.norm(differences[:, :3], axis=1)
    commanded_distance = float(np.linalg.norm(commanded_difference[:3]))
    mean_difference = differences.mean(axis=0)
    accuracy = mean_difference - commanded_difference
    accuracy[3:] = wrap_angle(accuracy[3:])
    spread = 3.0 * differences.std(axis=0, ddof=1)
    return DistanceCharacteristics(
        n=len(first),
        commanded_distance=commanded_distance,
        mean_distance=float(distances.mean()),
        ad_p=float(distances.mean() - commanded_distance),
        ad_x=float(accuracy[0]),
        ad_y=float(accuracy[1]),
        ad_z=float(accuracy[2]),
        ad_a=float(accuracy[3]),
        ad_b=float(accuracy[4]),
        ad_c=float(accuracy[5]),
        rd_p=float(3.0 * distances.std(ddof=1)),
        rd_x=float(spread[0]),
        rd_y=float(spread[1]),
        rd_z=float(spread[2]),
        rd_a=float(spread[3]),
        rd_b=float(spread[4]),
        rd_c=float(spread[5]),
    )


def multidirectional_variation(poses_by_direction: Sequence) -> MultiDirectionalVariation:
    """ISO 9283 multi-directional pose accuracy variation vAP from ≥ 2 approach directions.

    Parameters
    ----------
    poses_by_direction : sequence of (n_h, 6) arrays, one per approach direction (ISO uses 3)
    """
    if isinstance(poses_by_direction, np.ndarray) and poses_by_direction.ndim == 2:
        raise ISO9283Error("poses_by_direction: expected one (n, 6) array per approach direction, got a single array")
    sets = [as_poses(p, f"poses_by_direction[{h}]", minimum=1) for h, p in enumerate(poses_by_direction)]
    if len(sets) < 2:
        raise ISO9283Error(f"poses_by_direction: needs at least 2 approach directions, got {len(sets)}")
    centres = np.array([s.mean(axis=0) for s in sets])
    # One branch for all directions' mean angles (a set near ±π on both sides must not differ by 2π).
    for column in range(3, 6):
        reference = centres[0, column]
        centres[:, column] = reference + wrap_angle(centres[:, column] - reference)
    vap_p = max(float(np.linalg.norm(a[:3] - b[:3])) for a in centres for b in centres)
    spans = centres[:, 3:].max(axis=0) - centres[:, 3:].min(axis=0)
    centres[:, 3:] = wrap_angle(centres[:, 3:])
    return MultiDirectionalVariation(len(sets), centres, vap_p, float(spans[0]), float(spans[1]), float(spans[2]))


def pose_drift(first_poses, last_poses, commanded) -> PoseDrift:
    """ISO 9283 drift of pose characteristics between the first and the last measurement set.

    Parameters
    ----------
    first_poses, last_poses : (n, 6) arrays at the same commanded pose (e.g. the first and last
        cycles of a long run, per ISO 9283 §7.5)
    commanded : (6,) array
    """
    first = (pose_accuracy(first_poses, commanded), pose_repeatability(first_poses))
    last = (pose_accuracy(last_poses, commanded), pose_repeatability(last_poses))
    (ap1, rp1), (ap2, rp2) = first, last
    return PoseDrift(
        dap_p=abs(ap1.ap_p - ap2.ap_p),
        dap_a=abs(float(wrap_angle(ap1.ap_a - ap2.ap_a))),
        dap_b=abs(float(wrap_angle(ap1.ap_b - ap2.ap_b))),
        dap_c=abs(float(wrap_angle(ap1.ap_c - ap2.ap_c))),
        drp_l=abs(rp1.rp_l - rp2.rp_l),
        drp_a=abs(rp1.rp_a - rp2.rp_a),
        drp_b=abs(rp1.rp_b - rp2.rp_b),
        drp_c=abs(rp1.rp_c - rp2.rp_c),
        first=first,
        last=last,
    )
