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

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from instrument.pose._closed_form import _as_crosses, small_motion_pose
from instrument.pose._errors import InconsistentCrossesError, PoseError
from instrument.pose._geometry import SCREEN_NAMES, Geometry
from instrument.pose._lines import FAN_AXES, FANS, ScreenCross
from instrument.pose._rotation import Pose

DEFAULT_MAX_RESIDUAL_RMS = 100e-6  # m; noise-free calibrated data leaves ≪ 1 µm, pixel noise a few µm


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


class _StripeProblem:
    """Precomputed arrays of the 12 residuals (2 segment ends × 6 stripes).

    Residuals and Jacobian are computed together and cached on the parameter vector, because the
    optimiser asks for both at the same point; the rotation derivatives use
    ∂(R·e_j)/∂α = R·(e_x × e_j), ∂(R·e_j)/∂θ = (Rz(γ)·e_y) × (R·e_j), ∂(R·e_j)/∂γ = e_z × (R·e_j).
    """

    def __init__(self, crosses: Mapping[str, ScreenCross], geometry: Geometry) -> None:
        points, us, vs, normal_axes, self.fans = [], [], [], [], []
        for name in SCREEN_NAMES:
            screen = geometry.screens[name]
            for fan in FANS[name]:
                line = crosses[name].lines[fan]
                ends = line.point + np.outer([-line.half_length, line.half_length], line.direction)
                points.append(screen.to_frame(ends))
                us += [screen.u, screen.u]
                vs += [screen.v, screen.v]
                normal_axes += [FAN_AXES[fan][1]] * 2
                self.fans.append(fan)
        self.points = np.vstack(points)
        self.u = np.array(us)
        self.v = np.array(vs)
        self.normal_axes = np.array(normal_axes)
        # e_x × e_j = 0, e_z, −e_y for j = 0, 1, 2: the column of R it selects, and its sign.
        self.alpha_axes = np.array([0, 2, 1])[self.normal_axes]
        self.alpha_signs = np.array([0.0, 1.0, -1.0])[self.normal_axes]
        self._cached_x: bytes | None = None
        self._cached: tuple[np.ndarray, np.ndarray] | None = None

    def _evaluate(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = p.tobytes()
        if key == self._cached_x:
            return self._cached
        ca, sa, ct, st, cg, sg = np.cos(p[3]), np.sin(p[3]), np.cos(p[4]), np.sin(p[4]), np.cos(p[5]), np.sin(p[5])
        # Rows of R^T (= columns of R = R·e_j) of R = Rz(γ)·Ry(θ)·Rx(α), method.md eq. (4).
        rotation_t = np.array(
            [
                [cg * ct, sg * ct, -st],
                [cg * st * sa - sg * ca, sg * st * sa + cg * ca, ct * sa],
                [cg * st * ca + sg * sa, sg * st * ca - cg * sa, ct * ca],
            ]
        )
        normals = rotation_t[self.normal_axes]  # (12, 3): m = R·e_j per residual
        offsets = self.points - p[:3]
        mu = (normals * self.u).sum(axis=1)
        mv = (normals * self.v).sum(axis=1)
        sine = np.sqrt(mu * mu + mv * mv)
        numerator = (normals * offsets).sum(axis=1)
        residuals = numerator / sine
        jac = np.empty((len(sine), 6))
        jac[:, :3] = -normals / sine[:, None]
        # ∂r/∂m = (Q − t)/s − (m·(Q − t))/s³ · ((m·u)·u + (m·v)·v)
        d_normal = offsets / sine[:, None] - (residuals / (sine * sine))[:, None] * (
            mu[:, None] * self.u + mv[:, None] * self.v
        )
        jac[:, 3] = self.alpha_signs * (d_normal * rotation_t[self.alpha_axes]).sum(axis=1)
        m0, m1, m2 = normals[:, 0], normals[:, 1], normals[:, 2]
        n0, n1, n2 = d_normal[:, 0], d_normal[:, 1], d_normal[:, 2]
        # a × m with a = (a0, a1, 0): (a1·m2, −a0·m2, a0·m1 − a1·m0)
        jac[:, 4] = cg * m2 * n0 + sg * m2 * n1 + (-sg * m1 - cg * m0) * n2  # a = Rz(γ)·e_y = (−sγ, cγ, 0)
        jac[:, 5] = -m1 * n0 + m0 * n1  # a = e_z
        self._cached_x, self._cached = key, (residuals, jac)
        return residuals, jac

    def residuals(self, p: np.ndarray) -> np.ndarray:
        return self._evaluate(p)[0]

    def jacobian(self, p: np.ndarray) -> np.ndarray:
        return self._evaluate(p)[1]


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

    Raises
    ------
    MissingScreenError, CrossOffScreenError, StripeMatchError, InconsistentCrossesError, PoseError
    """
    crosses = _as_crosses(measurements, geometry)
    start = initial if initial is not None else small_motion_pose(crosses, geometry, lever="exact")
    problem = _StripeProblem(crosses, geometry)
    x0 = np.concatenate([start.translation, start.euler])
    result = least_squares(
        problem.residuals, x0, jac=problem.jacobian, method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-15, max_nfev=100
    )
    if not np.all(np.isfinite(result.x)):
        raise PoseError("pose solver diverged (non-finite parameters)")
    if abs(result.x[4]) > np.radians(80.0):
        raise PoseError(f"pose solver reached θ = {np.degrees(result.x[4]):.1f}°, near the Euler singularity")
    residuals = problem.residuals(result.x)
    rms = float(np.sqrt(np.mean(residuals**2)))
    per_stripe = {fan: float(np.sqrt(np.mean(residuals[2 * i : 2 * i + 2] ** 2))) for i, fan in enumerate(problem.fans)}
    if max_residual_rms is not None and not rms <= max_residual_rms:
        worst = max(per_stripe, key=per_stripe.get)
        raise InconsistentCrossesError(
            f"the three crosses do not come from one rigid pose: residual RMS {rms * 1e6:.1f} µm exceeds "
            f"{max_residual_rms * 1e6:.1f} µm (worst stripe: fan {worst!r}, {per_stripe[worst] * 1e6:.1f} µm); "
            "check the cameras' calibration and the screen assignment",
            residual_rms=rms,
            threshold=max_residual_rms,
        )
    pose = Pose.from_euler(result.x[:3], result.x[3:])
    return PoseEstimate(pose, rms, per_stripe, residuals, start, int(result.nfev))
