"""Synthetic ISO 9283 runs with known truth, for validating the budget and its propagation.

A seeded generator of what an instrument sees: the robot's true poses (static error per point,
scatter, a slow drift), and the measurement's errors drawn from a ``SyntheticCell``'s true
parameters — per-pose frame noise (optionally averaged over frames, optionally heavy-tailed), the
compensation's residual as a smooth random curve of the measured value, the interferometer's
scale and noise, the table encoder's error, the transform fit's and the environment's offsets.
The budget is then built *the way a real run builds it*, from estimates (the noise from the
frames or from a calibration noise floor with finite dof, the compensation's held-out RMS from
simulated held-out observations), not from the true parameters. Nothing here reads a file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from instrument._conventions import ARCSEC
from instrument.iso9283 import iso_cube_points
from instrument.uncertainty._budget import (
    BudgetTerm,
    Correlation,
    UncertaintyBudget,
    compensation_term,
    environment_term,
    interferometer_terms,
    rotary_table_term,
    transform_term,
)
from instrument.uncertainty._errors import UncertaintyError
from instrument.uncertainty._noise import frame_noise_from_calibration, frame_noise_from_frames
from instrument.uncertainty._propagate import IsoRun
from instrument.uncertainty._rotation import compose, euler_to_matrix

UM = 1e-6


def _six(position: float, angle: float) -> tuple[float, ...]:
    return (position,) * 3 + (angle,) * 3


@dataclass(frozen=True)
class SyntheticCell:
    """True parameters of the synthetic cell and run (SI: m, rad; relative for scales).

    The defaults follow the simulated cell's measured figures (README): robot σ = 10 µm and
    0.001° per axis, frame noise ≈ 1.1 µm / 1.1″, the compensation's residual a fraction of that.
    """

    cycles: int = 30
    cube_center: tuple[float, float, float] = (0.035, 0.035, 0.035)  # OPR positions, inside the calibration range
    cube_edge: float = 0.05
    tool_in_opr: tuple[float, ...] = (0.01, -0.02, 0.1, 0.0, 0.0, 0.0)  # [x, y, z, a, b, c]
    robot_accuracy: tuple[float, ...] = _six(50 * UM, 20 * ARCSEC)  # static error per point (σ)
    robot_repeatability: tuple[float, ...] = _six(10 * UM, 3.6 * ARCSEC)  # scatter per axis (σ)
    robot_drift: tuple[float, ...] = _six(0.05 * UM, 0.02 * ARCSEC)  # per cycle
    frame_noise: tuple[float, ...] = _six(1.1 * UM, 1.1 * ARCSEC)  # one frame, per component (σ)
    noise_tail_dof: float = math.inf  # Student-t noise with this dof (inf: normal)
    frames_per_pose: int = 1
    noise_estimator: str = "calibration"  # "calibration" | "frames" | "exact"
    calibration_dof: int = 90  # of the noise floor: 15 points × 3 groups × (3 − 1) repeats
    calibration_points: int = 15
    observations_per_point: int = 9
    compensation_model_error: tuple[float, ...] = _six(0.3 * UM, 0.3 * ARCSEC)  # RMS of the model's error curve
    calibration_step: tuple[float, ...] = _six(5e-3, math.radians(0.25))
    calibration_range: tuple[tuple[float, float], ...] = ((0.0, 0.07),) * 3 + ((-math.radians(1.75),
                                                                                  math.radians(1.75)),) * 3
    interferometer_scale: float = 0.3e-6  # standard uncertainty, rectangular
    interferometer_noise: float = 0.1 * UM
    encoder: float = 0.5 * ARCSEC / math.sqrt(3.0)
    transform_residual: float = 2 * UM
    transform_points: int = 6
    transform_spread: float = 0.03
    transform_lever: float = 0.03
    temperature_deviation: float = 0.5
    temperature_uncertainty: float = 0.1
    expansion_coefficient: float = 11.5e-6
    thermal_lever: float = 0.05
    directions: int = 0  # approach directions measured at P1 for vAP (0: none)
    direction_offset: tuple[float, ...] = _six(10 * UM, 3 * ARCSEC)  # robot's per-direction offset (σ)

    def __post_init__(self) -> None:
        if self.cycles < 2:
            raise UncertaintyError(f"cycles: expected ≥ 2, got {self.cycles}")
        if self.noise_estimator not in ("calibration", "frames", "exact"):
            raise UncertaintyError(
                f"noise_estimator: expected calibration, frames or exact, got {self.noise_estimator!r}")
        if self.noise_estimator == "frames" and self.frames_per_pose < 2:
            raise UncertaintyError("noise_estimator 'frames' needs frames_per_pose ≥ 2")


@dataclass(frozen=True)
class SyntheticIsoRun:
    """A synthetic run: the ``IsoRun`` (with ``truth``), the budget built from its data, the figure
    options, and the true values of the budget's inputs for reference."""

    run: IsoRun
    budget: UncertaintyBudget
    distance_pairs: tuple[tuple[str, str], ...]
    drift_cycles: int | None
    cell: SyntheticCell
    truth_parameters: dict[str, object] = field(default_factory=dict)


def smooth_error_curve(rms: float, step: float, span: tuple[float, float], rng: np.random.Generator):
    """A random smooth function of a value with RMS ``rms`` over ``span``: the sum of four sines with
    wavelengths of 2–6 calibration steps. Returns a vectorised callable."""
    wavelengths = rng.uniform(2.0, 6.0, size=4) * step
    phases = rng.uniform(0.0, 2.0 * np.pi, size=4)
    weights = rng.normal(size=4)
    grid = np.linspace(span[0], span[1], 401)

    def raw(v):
        v = np.asarray(v, dtype=float)
        return np.sum(weights * np.sin(2.0 * np.pi * v[..., None] / wavelengths + phases), axis=-1)

    norm = float(np.sqrt(np.mean(raw(grid) ** 2))) or 1.0
    return lambda v: rms * raw(v) / norm


def synthetic_iso_run(seed: int, cell: SyntheticCell | None = None) -> SyntheticIsoRun:
    """One seeded synthetic ISO 9283 run with its truth and the budget its data give.

    Parameters
    ----------
    seed : int
    cell : SyntheticCell, the true parameters (default: like the simulated cell)

    Returns
    -------
    SyntheticIsoRun
    """
    cell = cell or SyntheticCell()
    rng = np.random.default_rng(seed)
    n = cell.cycles
    cube = iso_cube_points(np.array(cell.cube_center), cell.cube_edge)
    names = list(cube.order)
    tool_rotation = euler_to_matrix(np.array(cell.tool_in_opr[3:]))
    tool_translation = np.array(cell.tool_in_opr[:3])

    # The robot: commanded OPR poses on the cube, a static error per point, scatter, drift.
    commanded_opr = {p: np.concatenate([cube.points[p], np.zeros(3)]) for p in names}
    trend = np.arange(n)[:, None] * np.array(cell.robot_drift)
    true_opr = {p: commanded_opr[p] + rng.normal(size=6) * cell.robot_accuracy
                + rng.normal(size=(n, 6)) * cell.robot_repeatability + trend for p in names}
    direction_true: list[np.ndarray] = []
    for _ in range(cell.directions):
        direction_true.append(true_opr["P1"].mean(axis=0) + rng.normal(size=6) * cell.direction_offset
                              + rng.normal(size=(n, 6)) * cell.robot_repeatability)

    # The instrument's errors, drawn once for the run (curves, scale, offsets) or per pose (noise).
    curves = {}
    for k in range(6):
        step, span = cell.calibration_step[k], cell.calibration_range[k]
        fit_noise = cell.frame_noise[k] / math.sqrt(cell.observations_per_point)
        curves[k] = [smooth_error_curve(rms, step, span, rng)
                     for rms in (cell.compensation_model_error[k], fit_noise)]
        curves[k].append(smooth_error_curve(cell.interferometer_noise if k < 3 else cell.encoder, step, span, rng))
    scale = rng.uniform(-1.0, 1.0) * math.sqrt(3.0) * cell.interferometer_scale
    budget_terms: list[BudgetTerm] = []
    transform = transform_term(cell.transform_residual, cell.transform_points, spread=cell.transform_spread,
                               lever=cell.transform_lever)
    environment = environment_term(cell.temperature_deviation, cell.expansion_coefficient, cell.thermal_lever,
                                   temperature_uncertainty=cell.temperature_uncertainty)
    transform_error = rng.normal(size=6) * np.array(transform.standard_uncertainty)
    thermal = cell.expansion_coefficient * cell.thermal_lever * (
        cell.temperature_deviation * rng.uniform(-1.0, 1.0, size=3) + cell.temperature_uncertainty * rng.normal(size=3))
    run_offset = transform_error + np.concatenate([thermal, np.zeros(3)])

    frames_seen: list[np.ndarray] = []

    def measure(opr_true: np.ndarray) -> np.ndarray:
        frames = opr_true[:, None, :] + _noise(rng, (len(opr_true), cell.frames_per_pose, 6), cell) * cell.frame_noise
        frames_seen.append(frames)
        opr = frames.mean(axis=1)
        value = opr.mean(axis=0)
        for k in range(6):
            opr[:, k] += sum(float(curve(value[k])) for curve in curves[k])
        opr[:, :3] += scale * opr_true[:, :3]
        return compose(opr, tool_rotation, tool_translation) + run_offset

    measured = {p: measure(true_opr[p]) for p in names}
    truth = {p: compose(true_opr[p], tool_rotation, tool_translation) for p in names}
    commanded = {p: compose(commanded_opr[p], tool_rotation, tool_translation) for p in names}
    directions = directions_truth = None
    if cell.directions >= 2:
        directions = {"P1": [measure(d) for d in direction_true]}
        directions_truth = {"P1": [compose(d, tool_rotation, tool_translation) for d in direction_true]}

    # The budget, as a real run would build it from its own estimates.
    budget_terms.append(_frame_noise_term(cell, np.concatenate(frames_seen), rng))
    budget_terms.append(_compensation_term(cell, curves, rng))
    budget_terms.extend(interferometer_terms(cell.interferometer_scale, cell.interferometer_noise,
                                             correlation_length=cell.calibration_step[0]))
    budget_terms.append(rotary_table_term(cell.encoder, correlation_length=cell.calibration_step[3],
                                          distribution="normal"))
    budget_terms.extend([transform, environment])
    run = IsoRun(measured=measured, commanded=commanded, tool_in_opr=np.array(cell.tool_in_opr), truth=truth,
                 directions=directions, directions_truth=directions_truth)
    drift_cycles = n // 3 if n >= 6 else None
    return SyntheticIsoRun(run, UncertaintyBudget(tuple(budget_terms)), (("P2", "P4"),), drift_cycles, cell,
                           {"scale": scale, "run_offset": run_offset.tolist()})


def _noise(rng: np.random.Generator, shape: tuple[int, ...], cell: SyntheticCell) -> np.ndarray:
    """Unit-variance frame noise: normal, or Student-t scaled to unit variance."""
    if math.isinf(cell.noise_tail_dof):
        return rng.standard_normal(shape)
    nu = cell.noise_tail_dof
    return rng.standard_t(nu, size=shape) * math.sqrt((nu - 2.0) / nu)


def _frame_noise_term(cell: SyntheticCell, frames: np.ndarray, rng: np.random.Generator) -> BudgetTerm:
    k = cell.frames_per_pose
    if cell.noise_estimator == "frames":
        return frame_noise_from_frames(frames, averaged=True)
    if cell.noise_estimator == "exact":
        return BudgetTerm("frame noise", "true value (synthetic)", Correlation.POSE,
                          tuple(s / math.sqrt(k) for s in cell.frame_noise))
    # The calibration's noise floor: the same instrument's noise (and the reference's), χ² with its dof.
    reference = (cell.interferometer_noise,) * 3 + (cell.encoder,) * 3
    floor = [math.sqrt((s**2 + r**2) * rng.chisquare(cell.calibration_dof) / cell.calibration_dof) / math.sqrt(k)
             for s, r in zip(cell.frame_noise, reference)]
    return frame_noise_from_calibration(dict(zip("xyzabc", floor)), cell.calibration_dof)


def _compensation_term(cell: SyntheticCell, curves, rng: np.random.Generator) -> BudgetTerm:
    """Held-out RMS and noise floor from simulated held-out observations at the interior points."""
    heldout, floor = {}, {}
    points = cell.calibration_points - 2  # the end points stay in training
    for k, component in enumerate("xyzabc"):
        lo, hi = cell.calibration_range[k]
        values = np.repeat(np.linspace(lo, hi, cell.calibration_points)[1:-1], cell.observations_per_point)
        reference = cell.interferometer_noise if k < 3 else cell.encoder
        sigma = math.hypot(cell.frame_noise[k], reference)
        errors = curves[k][0](values) + curves[k][1](values) + sigma * rng.standard_normal(values.size)
        heldout[component] = float(np.sqrt(np.mean(errors**2)))
        floor[component] = sigma * math.sqrt(rng.chisquare(cell.calibration_dof) / cell.calibration_dof)
    validity = dict(zip("xyzabc", cell.calibration_range))
    return compensation_term(heldout, noise_floor=floor, observations_per_point=cell.observations_per_point,
                             validity=validity, correlation_length=dict(zip("xyzabc", cell.calibration_step)),
                             dof=max(points, 3))
