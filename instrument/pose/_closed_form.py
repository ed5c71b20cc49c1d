"""The paper's closed form (Yu et al. 2023, eqs. 10–14): the small-motion direction-cosine model.

Derived here from the geometry (the printed eq. 14 has garbled subscripts):

- each cross's in-plane turn on screen k, measured from its stripes' nominal directions, is taken
  as the rotation about M's axis k: α from screen x, θ from screen y, γ from screen z, and
  R = Rz(γ)·Ry(θ)·Rx(α) (exact only to first order: the other two rotations tilt the cross too);
- the cross centre P_k on screen k is where the beam b = R·e_k from t meets the screen, so for each
  axis i ≠ k:  P_k,i = t_i + (P_k,k − t_k)·b_i / b_k  (the direction cosines r_ik / r_kk);
- the paper drops t_k on the right ("lever" = "paper"): t_i ≈ P_k,i − P_k,k·b_i/b_k, and each t_i is
  seen on two screens, which are averaged. With ``lever="exact"`` the six equations are instead
  solved for t by linear least squares, exact for the given R (the solver's starting point).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import cast

import numpy as np

from instrument.pose._errors import PoseError
from instrument.pose._geometry import AXIS_INDEX, SCREEN_NAMES, Geometry
from instrument.pose._lines import FANS, ScreenCross, nominal_directions, observe_crosses
from instrument.pose._rotation import Pose, euler_to_matrix


def _as_crosses(measurements: Mapping[str, object], geometry: Geometry) -> dict[str, ScreenCross]:
    if (
        isinstance(measurements, Mapping)
        and measurements
        and all(isinstance(m, ScreenCross) for m in measurements.values())
    ):
        if set(measurements) != set(SCREEN_NAMES):
            return observe_crosses(measurements, geometry)  # raises the missing-screen error
        return {name: cast(ScreenCross, cross) for name, cross in measurements.items()}
    return observe_crosses(measurements, geometry)


def cross_turn(cross: ScreenCross, geometry: Geometry) -> float:
    """In-plane turn of a cross on its screen from the identity pose, rad, positive u → v.

    The mean of both stripes' signed angles from their nominal directions (the paper's averaging).
    """
    nominal = nominal_directions(geometry.screens[cross.screen])
    total = 0.0
    for fan in FANS[cross.screen]:
        n0, n1 = float(nominal[fan][0]), float(nominal[fan][1])
        d0, d1 = (float(c) for c in cross.lines[fan].direction)
        total += math.atan2(n0 * d1 - n1 * d0, n0 * d0 + n1 * d1)
    return total / 2.0


def small_motion_pose(measurements: Mapping[str, object], geometry: Geometry, *, lever: str = "paper") -> Pose:
    """Closed-form OPR pose from three crosses (the paper's direction-cosine model).

    Parameters
    ----------
    measurements : mapping "x"/"y"/"z" → CrossMeasurement (or ScreenCross from ``observe_crosses``)
    geometry : Geometry
    lever : "paper" or "exact"
        "paper" drops the beam-axis translation from the lever arm, as the paper does; "exact"
        keeps it (linear least squares, exact for the estimated rotation).

    Returns
    -------
    Pose
        Good to first order in the motion; see docs/pose_and_iso.md for how far it departs from
        ``solve_pose`` as the pose grows.
    """
    if lever not in ("paper", "exact"):
        raise ValueError(f"lever: expected 'paper' or 'exact', got {lever!r}")
    translation, rotation, _ = closed_form(_as_crosses(measurements, geometry), geometry, lever)
    return Pose(translation, rotation)


def closed_form(crosses: Mapping[str, ScreenCross], geometry: Geometry, lever: str = "exact"):
    """(translation, rotation, (α, θ, γ)) of the closed form, from crosses already on the screens."""
    alpha, theta, gamma = (cross_turn(crosses[name], geometry) for name in SCREEN_NAMES)
    rotation = euler_to_matrix(alpha, theta, gamma)
    rows, rhs = [], []
    estimates: dict[int, list[float]] = {0: [], 1: [], 2: []}
    for name in SCREEN_NAMES:
        k = AXIS_INDEX[name]
        beam = rotation[:, k].tolist()
        if abs(beam[k]) < 1e-6:
            raise PoseError(f"screen {name!r}: the beam runs parallel to the screen")
        hit = crosses[name].center_m.tolist()
        for i in range(3):
            if i == k:
                continue
            slope = beam[i] / beam[k]  # direction cosine ratio r_ik / r_kk
            estimates[i].append(hit[i] - hit[k] * slope)
            row = [0.0, 0.0, 0.0]
            row[i], row[k] = 1.0, -slope
            rows.append(row)
            rhs.append(hit[i] - hit[k] * slope)
    if lever == "paper":
        translation = np.array([sum(estimates[i]) / len(estimates[i]) for i in range(3)])
    else:
        design = np.array(rows)
        translation = np.linalg.solve(
            design.T @ design, design.T @ np.array(rhs)
        )  # well conditioned: rows ≈ unit vectors
    return translation, rotation, (alpha, theta, gamma)
