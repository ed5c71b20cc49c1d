"""Per-frame measurement noise, estimated from the run's own data (three estimators).

Which one to use:

- ``frame_noise_from_frames``: several frames per pose whose noise is independent (speckle that
  decorrelates between frames, e.g. a moving diffuser). The pooled scatter between the frames of
  one pose is a direct Type A estimate. Refused when the frames are identical (the simulated
  camera renders one image per settled pose: averaging it measures nothing).
- ``frame_noise_from_residuals``: one frame per pose. The pose solver's fit residual (12 stripe
  residuals, 6 unknowns) estimates the stripe noise σ_r² = Σr²/(m − 6), pooled over the run's
  poses, and the solver's Jacobian J carries it to the pose: cov = σ_r²·(JᵀJ)⁻¹. Valid when the
  stripe residuals are independent with equal variance; noise that moves a whole cross (a
  shifted screen) leaves no residual and is missed.
- ``frame_noise_from_calibration``: the calibration's noise floor (pooled repeat scatter of
  measured − reference at each calibration point and group). The robot's own scatter cancels in
  measured − reference; the reference's noise does not, so it is slightly conservative. Use it
  as the fallback, or as a cross-check of the other two.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from instrument.uncertainty._budget import COMPONENTS, MINIMUM_DOF, BudgetTerm, Correlation, per_component
from instrument.uncertainty._errors import UncertaintyError

NAME = "frame noise"


def frame_noise_from_frames(frames, *, averaged: bool = True) -> BudgetTerm:
    """Pooled between-frame scatter of each pose's frames.

    Parameters
    ----------
    frames : (n_poses, k, 6) array, the OPR pose [x, y, z, a, b, c] (m, rad) solved from each of
        k ≥ 2 frames of every pose
    averaged : bool
        True when the run's pose is the mean of the k frames (its noise is σ/√k), False when it is
        one of them.

    Returns
    -------
    BudgetTerm
        Correlation POSE, dof = n_poses·(k − 1).
    """
    array = np.asarray(frames, dtype=float)
    if array.ndim != 3 or array.shape[2] != 6 or array.shape[1] < 2 or array.shape[0] < 1:
        raise UncertaintyError(f"frames: expected (n_poses, k ≥ 2, 6) poses, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise UncertaintyError("frames: non-finite pose value")
    n_poses, k = array.shape[:2]
    deviations = array - array.mean(axis=1, keepdims=True)
    dof = n_poses * (k - 1)
    sigma = np.sqrt((deviations**2).sum(axis=(0, 1)) / dof)
    if not np.all(sigma > 0):
        identical = [c for c, s in zip(COMPONENTS, sigma) if s == 0]
        raise UncertaintyError(f"frames: identical frames in component(s) {', '.join(identical)}; the scatter "
                               "between frames cannot estimate the noise (the same image seen twice?)")
    if averaged:
        sigma = sigma / np.sqrt(k)
    return BudgetTerm(NAME, f"pooled scatter between the {k} frames of {n_poses} poses"
                      + (f" (pose = mean of {k} frames)" if averaged else ""),
                      Correlation.POSE, tuple(float(s) for s in sigma), dof=max(float(dof), MINIMUM_DOF))


def frame_noise_from_residuals(residual_rms, jacobian, *, n_residuals: int = 12) -> BudgetTerm:
    """The pose solver's fit residual propagated through its Jacobian.

    Parameters
    ----------
    residual_rms : (n_poses,) array, the solver's RMS of its ``n_residuals`` residuals at each
        solution (m)
    jacobian : (n_residuals, 6) or (n_poses, n_residuals, 6) array, ∂residual/∂(x, y, z, a, b, c)
        at the solution(s) (m per m, m per rad)
    n_residuals : int, residuals per pose (12: 6 stripes × 2 ends)

    Returns
    -------
    BudgetTerm
        Correlation POSE, u_k = σ_r·√(mean over poses of [(JᵀJ)⁻¹]_kk), dof = n_poses·(m − 6).
    """
    rms = np.asarray(residual_rms, dtype=float).reshape(-1)
    m = int(n_residuals)
    if m <= 6:
        raise UncertaintyError(f"n_residuals: needs more than 6 residuals for 6 unknowns, got {n_residuals}")
    if rms.size == 0 or not np.all(np.isfinite(rms)) or np.any(rms < 0):
        raise UncertaintyError("residual_rms: expected finite values ≥ 0, one per pose")
    jac = np.asarray(jacobian, dtype=float)
    if jac.shape == (m, 6):
        jac = jac[None]
    if jac.ndim != 3 or jac.shape[1:] != (m, 6) or jac.shape[0] not in (1, rms.size):
        raise UncertaintyError(f"jacobian: expected ({m}, 6) or ({rms.size}, {m}, 6), got shape {np.shape(jacobian)}")
    normal = np.einsum("pri,prj->pij", jac, jac)
    try:
        gains = np.diagonal(np.linalg.inv(normal), axis1=1, axis2=2).mean(axis=0)
    except np.linalg.LinAlgError:
        raise UncertaintyError("jacobian: JᵀJ is singular; the residuals do not determine the pose") from None
    dof = rms.size * (m - 6)
    sigma_r2 = float(np.sum(m * rms**2) / dof)
    if sigma_r2 == 0:
        raise UncertaintyError("residual_rms: all zero; a noise-free fit cannot estimate the noise")
    sigma = np.sqrt(sigma_r2 * gains)
    return BudgetTerm(NAME, f"pose solver residual (σ_r = {np.sqrt(sigma_r2):.3g} m over {rms.size} poses) "
                      "through the solver's Jacobian", Correlation.POSE, tuple(float(s) for s in sigma),
                      dof=max(float(dof), MINIMUM_DOF))


def frame_noise_from_calibration(noise_floor: Mapping[str, float], dof: Mapping[str, float] | float) -> BudgetTerm:
    """The calibration records' noise floor (repeat scatter of measured − reference) per component.

    Parameters
    ----------
    noise_floor : mapping component → pooled repeat standard deviation (m or rad)
    dof : its degrees of freedom (one number, or one per component; the smallest is used)
    """
    sigma = per_component(noise_floor, "noise_floor")
    values = list(dof.values()) if isinstance(dof, Mapping) else [dof]
    smallest = min(float(v) for v in values)
    if not smallest >= MINIMUM_DOF:
        raise UncertaintyError(f"dof: expected ≥ {MINIMUM_DOF:g}, got {smallest}")
    return BudgetTerm(NAME, "calibration noise floor (repeat scatter of measured − reference; includes the "
                      "reference's noise)", Correlation.POSE, sigma, dof=smallest)
