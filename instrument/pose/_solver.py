"""Exact 6-DOF pose from three crosses: nonlinear least squares on the stripe lines (method.md §3).

Unknowns p = (t_x, t_y, t_z, α, θ, γ). Each measured stripe contributes two residuals: the in-screen
distances of the two ends of its observed segment from the stripe line the pose predicts. For a
point Q on the screen and the fan plane through t with unit normal m = R·e_j, that distance is

    r = m·(Q − t) / |(m·u, m·v)|,

exact (the plane's offset divided by the sine of its angle with the screen) and cheap to
differentiate, so the Jacobian is analytic. 6 stripes × 2 ends = 12 residuals in metres; weighting
by the observed segment length gives the line angles their proper weight.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from instrument.pose._closed_form import _as_crosses, closed_form
from instrument.pose._errors import InconsistentCrossesError, PoseError
from instrument.pose._geometry import SCREEN_NAMES, Geometry
from instrument.pose._lines import FAN_AXES, FANS, ScreenCross
from instrument.pose._rotation import Pose, trusted_pose

DEFAULT_MAX_RESIDUAL_RMS = 100e-6  # m; noise-free calibrated data leaves ≪ 1 µm, pixel noise a few µm
_MAX_ITERATIONS = 50
_STOP_STEP = 1e-9  # rad (translation per 0.1 m): a Gauss–Newton step this small is the last one
_STEP_FLOOR = 1e-13  # any step this small (even a damped one): nothing left to gain
_DIAGONAL = (np.arange(6), np.arange(6))
_END_SIGNS = np.tile([-1.0, 1.0], 6)
_ROWS = np.arange(12)[:, None]


@dataclass(frozen=True)
class PoseEstimate:
    """A solved OPR pose in M with its consistency figures.

    Attributes
    ----------
    pose : Pose
    residual_rms : float
        RMS of the 12 stripe residuals at the solution, m.
    stripe_residuals : dict fan → float
        RMS of each stripe's two residuals, m (fans "xy", "xz", "yz", "yx", "zx", "zy").
    residuals : (12,) array
        Signed residuals, m, two per stripe in the order of ``stripe_residuals``.
    start : Pose
        The closed-form starting point.
    evaluations : int
        Residual evaluations the optimiser used.
    """

    pose: Pose
    residual_rms: float
    stripe_residuals: dict[str, float]
    residuals: np.ndarray = field(repr=False)
    start: Pose = field(repr=False)
    evaluations: int = 0

    @property
    def translation(self) -> np.ndarray:
        return self.pose.translation

    @property
    def rotation(self) -> np.ndarray:
        return self.pose.rotation

    @property
    def euler(self) -> np.ndarray:
        """(α, θ, γ), rad, R = Rz(γ)·Ry(θ)·Rx(α)."""
        return self.pose.euler


def _static_arrays(geometry: Geometry):
    """What depends on the station only: the fan of each stripe, and per residual (2 per stripe,
    screens x, y, z, fans in FANS order) the screen's origin, u and v, the column index of R[k, j]
    in R.ravel() for k = 0, 1, 2 (j the OPR axis of the fan's normal m = R·e_j), and the moment
    matrix's constant rows: m·u, m·v and m itself."""
    fans, origins, us, vs, normal_axes = [], [], [], [], []
    for name in SCREEN_NAMES:
        screen = geometry.screens[name]
        for fan in FANS[name]:
            fans.append(fan)
            origins += [screen.origin] * 2
            us += [screen.u] * 2
            vs += [screen.v] * 2
            normal_axes += [FAN_AXES[fan][1]] * 2
    axes = np.array(normal_axes)
    columns = 3 * np.arange(3)[None, :] + axes[:, None]  # (12, 3): R[k, j] sits at 3k + j
    # rows 0–11: m·(Q − t) (filled per evaluation); 12–23: m·u; 24–35: m·v; 36–71: m (k = 0, 1, 2)
    moments = np.zeros((72, 9))
    rows = np.arange(12)[:, None]
    moments[12 + rows, columns] = np.array(us)
    moments[24 + rows, columns] = np.array(vs)
    moments[36 + 3 * rows + np.arange(3)[None, :], columns] = 1.0
    return fans, np.array(origins), np.array(us), np.array(vs), columns, moments


def _rotation_and_derivatives(alpha: float, theta: float, gamma: float) -> np.ndarray:
    """(9, 4): R.ravel() and the ravelled ∂R/∂α, ∂R/∂θ, ∂R/∂γ of R = Rz(γ)·Ry(θ)·Rx(α) as columns."""
    ca, sa, ct, st = math.cos(alpha), math.sin(alpha), math.cos(theta), math.sin(theta)
    cg, sg = math.cos(gamma), math.sin(gamma)
    return np.array(
        [
            [cg * ct, 0.0, -cg * st, -sg * ct],
            [cg * st * sa - sg * ca, cg * st * ca + sg * sa, cg * ct * sa, -sg * st * sa - cg * ca],
            [cg * st * ca + sg * sa, -cg * st * sa + sg * ca, cg * ct * ca, -sg * st * ca + cg * sa],
            [sg * ct, 0.0, -sg * st, cg * ct],
            [sg * st * sa + cg * ca, sg * st * ca - cg * sa, sg * ct * sa, cg * st * sa - sg * ca],
            [sg * st * ca - cg * sa, -sg * st * sa - cg * ca, sg * ct * ca, cg * st * ca + sg * sa],
            [-st, 0.0, -ct, 0.0],
            [ct * sa, ct * ca, -st * sa, 0.0],
            [ct * ca, -ct * sa, -st * ca, 0.0],
        ]
    )


class _StripeProblem:
    """The 12 residuals (2 segment ends × 6 stripes) and their analytic Jacobian.

    With m = R·e_j the fan's normal, Q a segment end and (u, v) its screen's axes, every quantity
    the residual r = m·(Q − t) / |(m·u, m·v)| needs is linear in the entries of R: m·Q, m·u and m·v
    (and their derivatives in α, θ, γ) come from one (36 × 9) @ (9 × 4) product of a moment matrix
    with R and ∂R/∂(α, θ, γ); m·t and its derivatives from Rᵀ·t.
    """

    def __init__(self, crosses: Mapping[str, ScreenCross], geometry: Geometry) -> None:
        static = geometry.cache.get("stripe_problem")
        if static is None:  # computed once per Geometry
            static = _static_arrays(geometry)
            geometry.cache["stripe_problem"] = static
        self.fans, origins, u, v, columns, moments = static
        rows = []
        for name in SCREEN_NAMES:
            lines = crosses[name].lines
            for fan in FANS[name]:
                line = lines[fan]
                rows.append((*line.point, *line.direction, line.half_length))
        point_u, point_v, direction_u, direction_v, half = np.repeat(np.array(rows).T, 2, axis=1)
        ends = half * _END_SIGNS  # the two ends of each observed segment, along it
        a = point_u + ends * direction_u
        b = point_v + ends * direction_v
        self.points = origins + a[:, None] * u + b[:, None] * v  # (12, 3) segment ends Q in M
        self.moments = moments.copy()
        self.target = (_ROWS, columns)  # where Q − t goes in the moment matrix
        self.evaluations = 0

    def evaluate(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (12,) m and Jacobian (12, 6) at p = (t, α, θ, γ)."""
        self.evaluations += 1
        self.moments[self.target] = self.points - p[:3]
        # (72, 4): m·(Q − t), m·u, m·v, m — and, in columns 1–3, their derivatives in α, θ, γ
        products = self.moments @ _rotation_and_derivatives(p[3], p[4], p[5])
        numerator, mu, mv = products[:12], products[12:24], products[24:36]
        inverse_sine = 1.0 / np.sqrt(mu[:, 0] * mu[:, 0] + mv[:, 0] * mv[:, 0])
        residuals = numerator[:, 0] * inverse_sine
        jac = np.empty((12, 6))
        np.multiply(products[36:, 0].reshape(12, 3), -inverse_sine[:, None], out=jac[:, :3])  # ∂r/∂t = −m/s
        # ∂r = ∂(m·(Q − t))/s − r·(m·u ∂(m·u) + m·v ∂(m·v))/s²
        slope = mu[:, :1] * mu[:, 1:]
        slope += mv[:, :1] * mv[:, 1:]
        slope *= (residuals * inverse_sine)[:, None]
        np.subtract(numerator[:, 1:], slope, out=jac[:, 3:])
        jac[:, 3:] *= inverse_sine[:, None]
        return residuals, jac


def _step_size(step: np.ndarray) -> float:
    """Largest move of a step, rad, the translation counted per 0.1 m (the scale of the lever arms)."""
    return max(abs(step[0]) * 10.0, abs(step[1]) * 10.0, abs(step[2]) * 10.0, abs(step[3]), abs(step[4]), abs(step[5]))


def _least_squares(problem: _StripeProblem, x0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg–Marquardt for the 12 × 6 problem (Marquardt's diagonal scaling).

    Starts as plain Gauss–Newton (λ = 0), which converges quadratically from the closed form or
    from the previous pose of a stream; λ grows tenfold only when a step fails to lower the cost.
    A Gauss–Newton step smaller than ``_STOP_STEP`` (rad, or × 0.1 m) is applied without a further
    evaluation: what remains after it is of the order of its square (≲ 1e-17). The residuals at
    the final point are then the last evaluated ones plus J·step (exact to that same order).
    Returns (parameters, residuals).
    """
    x = x0.astype(float)
    residuals, jac = problem.evaluate(x)
    cost = float(residuals @ residuals)
    damping = 0.0
    for _ in range(_MAX_ITERATIONS):
        normal = jac.T @ jac
        gradient = jac.T @ residuals
        if damping > 0.0:
            normal[_DIAGONAL] *= 1.0 + damping
        try:
            step = -np.linalg.solve(normal, gradient)
        except np.linalg.LinAlgError:
            damping = max(10.0 * damping, 1e-6)
            continue
        if not np.all(np.isfinite(step)):
            raise PoseError("pose solver diverged (non-finite step)")
        size = _step_size(step)
        if (damping == 0.0 and size < _STOP_STEP) or size < _STEP_FLOOR:
            return x + step, residuals + jac @ step
        candidate = x + step
        new_residuals, new_jac = problem.evaluate(candidate)
        new_cost = float(new_residuals @ new_residuals)
        if new_cost <= cost * (1.0 + 1e-12) + 1e-300:
            x, residuals, jac, cost = candidate, new_residuals, new_jac, new_cost
            damping = 0.0 if damping < 1e-9 else 0.1 * damping
        else:
            damping = max(10.0 * damping, 1e-6)
    raise PoseError(f"pose solver did not converge in {_MAX_ITERATIONS} iterations (residual RMS "
                    f"{np.sqrt(cost / len(residuals)) * 1e6:.1f} µm)")


def solve_pose(
    measurements: Mapping[str, object],
    geometry: Geometry,
    *,
    max_residual_rms: float | None = DEFAULT_MAX_RESIDUAL_RMS,
    initial: Pose | None = None,
) -> PoseEstimate:
    """Exact OPR pose in M from the three crosses.

    Parameters
    ----------
    measurements : mapping "x"/"y"/"z" → CrossMeasurement (pixels), or ScreenCross (``observe_crosses``)
    geometry : Geometry
    max_residual_rms : float or None
        Residual RMS (m) above which the crosses are declared inconsistent with one rigid pose
        (``InconsistentCrossesError``); None disables the check.
    initial : Pose, optional
        Starting point; by default the closed form (``small_motion_pose(..., lever="exact")``).
        A stream passes the previous sample's pose (a warm start: the closed form is skipped).

    Returns
    -------
    PoseEstimate

    Raises
    ------
    MissingScreenError, CrossOffScreenError, StripeMatchError, InconsistentCrossesError, PoseError
    """
    crosses = _as_crosses(measurements, geometry)
    if initial is None:
        translation, _, euler = closed_form(crosses, geometry, lever="exact")
        x0 = np.array([*translation, *euler])
        start = trusted_pose(x0[:3], x0[3:])
    else:
        start = initial
        x0 = np.concatenate([start.translation, start.euler])
    problem = _StripeProblem(crosses, geometry)
    x, residuals = _least_squares(problem, x0)
    if not np.all(np.isfinite(x)):
        raise PoseError("pose solver diverged (non-finite parameters)")
    if abs(x[4]) > np.radians(80.0):
        raise PoseError(f"pose solver reached θ = {np.degrees(x[4]):.1f}°, near the Euler singularity")
    rms = math.sqrt(float(residuals @ residuals) / len(residuals))
    pairs = residuals.reshape(6, 2)
    per_stripe = dict(zip(problem.fans, np.sqrt(0.5 * np.einsum("ij,ij->i", pairs, pairs)).tolist()))
    if max_residual_rms is not None and not rms <= max_residual_rms:
        worst = max(per_stripe, key=lambda fan: per_stripe[fan])
        raise InconsistentCrossesError(
            f"the three crosses do not come from one rigid pose: residual RMS {rms * 1e6:.1f} µm exceeds "
            f"{max_residual_rms * 1e6:.1f} µm (worst stripe: fan {worst!r}, {per_stripe[worst] * 1e6:.1f} µm); "
            "check the cameras' calibration and the screen assignment",
            residual_rms=rms,
            threshold=max_residual_rms,
        )
    pose = trusted_pose(x[:3], x[3:])  # x is finite (checked above)
    return PoseEstimate(pose, rms, per_stripe, residuals, start, problem.evaluations)
