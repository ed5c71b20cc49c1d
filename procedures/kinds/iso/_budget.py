"""The uncertainty budget of an ISO 9283 run, built from the run's own data and its calibration records.

Which number comes from where (docs/uncertainty.md, "Wiring it into a run", has the reasoning):

- **frame noise**: the calibration records' noise floor per component (pooled repeat scatter of
  measured − reference), dof = observations − cells. Why this estimator: the simulated camera
  renders one image per settled pose, so the scatter between the frames of a pose is zero there
  (``frame_noise_from_frames`` refuses it), and a real camera's frames share the speckle of a
  settled pose unless a moving diffuser decorrelates it, so their scatter would miss the dominant
  noise; the solver-residual estimator needs the solver's Jacobian, which ``instrument.pose`` does
  not export. The floor holds every per-pose error (speckle, camera, reference noise): conservative.
  Scaled by √(k_cal/k_run) when the run averages fewer frames than the calibration did; the frames'
  scatter is kept as a cross-check when it is not zero.
- **compensation residual**: per component, the record in force: held-out (leave-one-point-out)
  RMS of its method less the noise floor in quadrature, its validity range, ℓ = the calibration
  step; a component measured without compensation: the record's uncompensated held-out RMS.
- **interferometer scale, noise**: the displacement record's reference (wavelength-compensation
  residual, reading noise); **rotary table encoder**: the angle record's reference (±0.5″ class).
- **transform fit**: the measurement error of the transform pass (frame noise and compensation
  residual per point) through the rigid fit, not its residual, which holds the robot's own scatter.
- **environment**: the instrument's thermal scale: aluminium (23e-6 /K) × the air's difference
  from the calibration's (both from the environmental unit; ±1 K when either is unknown).
- **off-axis angle error**: the angles' error that depends on the position (which a curve of each
  angle's own value cannot correct), from the displacement calibration's slopes of a, b, c along
  the x, y, z lines (``_calibration_results.off_axis_slopes``), at the run's points. Carried in U,
  not corrected: the slopes hold the robot's own angular deviation along a line too.
- **frame shear, frame rotation**: the position frame's squareness and its rotation against the
  angle frame, which neither calibration measures; in U only when stated
  (``frame_squareness_urad``), else the run says it is left out.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from instrument import COMPONENTS
from instrument.uncertainty import (
    BudgetTerm,
    Correlation,
    Distribution,
    UncertaintyBudget,
    UncertaintyError,
    compensation_term,
    frame_noise_from_calibration,
    frame_noise_from_frames,
    interferometer_terms,
    rotary_table_term,
)
from procedures.kinds._references import (
    HENE_WAVELENGTH_M,
    INTERFEROMETER_READING_NOISE_M,
    TABLE_ENCODER_UNCERTAINTY_RAD,
    scale_uncertainty,
)

INSTRUMENT_EXPANSION_PER_K = 23e-6  # the screens' frame: aluminium
UNKNOWN_TEMPERATURE_HALF_WIDTH_K = 1.0
AIR_SENSOR_UNCERTAINTY_K = 0.2 / math.sqrt(3.0)
MINIMUM_DOF = 3.0
LINEAR = ("x", "y", "z")
ANGULAR = ("a", "b", "c")


class BudgetUnavailable(Exception):
    """The run's data cannot give a budget (the one-line reason)."""


def component_sources(infos: Sequence[Mapping[str, Any]]) -> dict[str, Mapping[str, Any]]:
    """Per component, the first record (its ``info()``) whose evaluation covers it."""
    out: dict[str, Mapping[str, Any]] = {}
    for info in infos:
        for component in (info.get("evaluation") or {}):
            out.setdefault(component, info)
    return out


def _step(info: Mapping[str, Any], component: str) -> float | None:
    evaluation = info["evaluation"][component]
    lo, hi = (info.get("validity") or {}).get(component, (None, None))
    points = evaluation.get("n_points")
    if lo is None or hi is None or not points or points < 2:
        return None
    return (float(hi) - float(lo)) / (int(points) - 1)


def _noise_dof(evaluation: Mapping[str, Any]) -> float:
    observations = evaluation.get("n_observations") or 0
    cells = (evaluation.get("n_points") or 0) * (evaluation.get("n_groups") or 1) * max(
        1, len(evaluation.get("directions") or []))
    return max(float(observations - cells), MINIMUM_DOF)


def _reference(info: Mapping[str, Any] | None, instrument: str) -> Mapping[str, Any]:
    for reference in (info or {}).get("references") or []:
        if reference.get("instrument") == instrument:
            return reference
    return {}


def frame_noise_term(sources: Mapping[str, Mapping[str, Any]], frames_per_pose: int,
                     per_frame: Sequence[Sequence[Sequence[float]]] | None) -> tuple[BudgetTerm, dict[str, Any]]:
    """The frame-noise term from the records' noise floors, and what the estimator was (for the results)."""
    missing = [c for c in COMPONENTS if c not in sources]
    if missing:
        raise BudgetUnavailable(f"no calibration record gives the noise floor of {', '.join(missing)} (the frame "
                                "noise estimate); calibrate them and put the records in force")
    floors, dofs, scales = {}, {}, {}
    for c in COMPONENTS:
        info = sources[c]
        frames = next((r.get("frames_per_pose") for r in info.get("references") or [] if r.get("frames_per_pose")),
                      None)
        scales[c] = math.sqrt(max(1.0, float(frames) / frames_per_pose)) if frames else 1.0
        floors[c] = float(info["evaluation"][c]["noise_floor"]) * scales[c]
        dofs[c] = _noise_dof(info["evaluation"][c])
    term = frame_noise_from_calibration(floors, dofs)
    cross_check = None
    if per_frame is not None and len(per_frame) and len(per_frame[0]) >= 2:
        try:
            frames_term = frame_noise_from_frames(np.asarray(per_frame, dtype=float), averaged=True)
            cross_check = dict(zip(COMPONENTS, frames_term.standard_uncertainty))
        except UncertaintyError:
            cross_check = None  # identical frames (the simulated camera): they say nothing about the noise
    estimator = {
        "used": "calibration noise floor",
        "why": ("one image per settled pose: the simulated camera renders one, a real one shares the pose's speckle "
                "unless a diffuser moves, so the scatter between frames misses the dominant noise; the solver's "
                "Jacobian (for the residual estimator) is not exported. The floor holds every per-pose error "
                "(speckle, camera, reference noise): conservative."),
        "records": sorted({str(sources[c].get("id")) for c in COMPONENTS}),
        "standard_uncertainty": dict(zip(COMPONENTS, term.standard_uncertainty)), "dof": term.dof,
        "frames_scale": scales, "frames_cross_check": cross_check,
    }
    return term, estimator


def compensation_residual_term(sources: Mapping[str, Mapping[str, Any]], applied: set[str]) -> BudgetTerm:
    """The records' held-out residual (applied components) or raw error (components not corrected)."""
    heldout, floors, validity, dofs = {}, {}, {}, []
    lengths: dict[str, float | None] = {}
    observations = []
    for c in COMPONENTS:
        info = sources[c]
        evaluation = info["evaluation"][c]
        lengths[c] = _step(info, c)
        if c in applied:
            heldout[c] = float(evaluation["heldout_rms"])
            floors[c] = float(evaluation["noise_floor"])
            lo, hi = info["validity"][c]
            validity[c] = (float(lo), float(hi))
            if evaluation.get("n_points"):
                observations.append(int(evaluation["n_observations"]) / int(evaluation["n_points"]))
                dofs.append(max(float(evaluation["n_points"]) - 2.0, MINIMUM_DOF))
        else:
            raw = evaluation.get("uncompensated_rms")
            if raw is None:
                raise BudgetUnavailable(f"{c} is not compensated and its record states no uncompensated error")
            heldout[c] = float(raw)
    per_point = int(round(min(observations))) if observations else 9
    term = compensation_term(heldout, noise_floor=floors or None, observations_per_point=max(per_point, 1),
                             validity=validity or None,
                             correlation_length={c: v for c, v in lengths.items() if v is not None},
                             dof=min(dofs) if dofs else math.inf)
    if len(applied) < len(COMPONENTS):
        raw = ", ".join(c for c in COMPONENTS if c not in applied)
        term = BudgetTerm(term.name, term.source + f"; not compensated ({raw}): the record's uncompensated held-out "
                          "RMS", term.correlation, term.standard_uncertainty, dof=term.dof,
                          correlation_length=term.correlation_length, validity=term.validity)
    return term


def reference_terms(sources: Mapping[str, Mapping[str, Any]]) -> list[BudgetTerm]:
    """The interferometer's scale and noise and the table's encoder, from the records' references."""
    displacement = _reference(sources.get("x"), "laser interferometer")
    scale = displacement.get("scale_standard_uncertainty")
    if scale is None:  # a record written before the references stated it: taken as not compensated
        scale = scale_uncertainty(None, HENE_WAVELENGTH_M, compensated=False)
    noise = float(displacement.get("reading_noise_m", INTERFEROMETER_READING_NOISE_M))
    linear_step = _step(sources["x"], "x") if "x" in sources else None
    scale_term, noise_term = interferometer_terms(float(scale), noise, correlation_length=linear_step,
                                                  scale_distribution=Distribution.NORMAL)
    angle = _reference(sources.get("a"), "rotary table encoder")
    encoder = float(angle.get("encoder_standard_uncertainty_rad", TABLE_ENCODER_UNCERTAINTY_RAD))
    angle_step = _step(sources["a"], "a") if "a" in sources else None
    return [scale_term, noise_term, rotary_table_term(encoder, correlation_length=angle_step)]


def transform_fit_term(noise: BudgetTerm, compensation: BudgetTerm, n_points: int, spread: float,
                       lever: float) -> BudgetTerm:
    """The rigid fit's error from the measurement error of its points (one offset for the run).

    Per coordinate σ² = noise² + compensation residual² (mean over x, y, z); the fit of ``n_points``
    points with RMS distance ``spread`` from their centroid has u = σ/√n at the centroid and a
    rotation σ/(√n·ρ), which moves a point at ``lever`` by σ/√n·L/ρ.
    """
    sigma = math.sqrt(float(np.mean([noise.standard_uncertainty[k] ** 2 + compensation.standard_uncertainty[k] ** 2
                                     for k in range(3)])))
    n = max(int(n_points), 3)
    u_position = sigma / math.sqrt(n) * math.sqrt(1.0 + (lever / spread) ** 2)
    u_angle = sigma / (math.sqrt(n) * spread)
    return BudgetTerm("transform fit", f"rigid fit of {n} measured points, σ = {sigma:.3g} m per coordinate "
                      "(frame noise and compensation residual; the fit residual holds the robot's own scatter)",
                      Correlation.RUN, (u_position,) * 3 + (u_angle,) * 3, dof=max(noise.dof, MINIMUM_DOF))


def off_axis_error(slopes: Mapping[str, Mapping[str, float]], position: Sequence[float]) -> np.ndarray:
    """(6,) error of each component at ``position`` (m, in M) from the other axes' slopes."""
    error = np.zeros(6)
    for axis, row in slopes.items():
        k = COMPONENTS.index(axis)
        for component, slope in row.items():
            error[COMPONENTS.index(component)] += float(slope) * float(position[k])
    return error


def off_axis_terms(sources: Mapping[str, Mapping[str, Any]], positions: Mapping[str, Sequence[float]]
                   ) -> tuple[BudgetTerm | None, dict[str, Any] | None]:
    """The off-axis angle error at the run's points (a point term on a, b, c) and its figures.

    Only the angles: along a calibration line the robot holds its orientation, so the angles' slopes
    are the instrument's; the positions' slopes also hold the robot's line direction in M, which the
    calibration cannot know (see ``squareness_terms``). None when the displacement record states no
    slopes.
    """
    off_axis = _reference(sources.get("x"), "laser interferometer").get("off_axis") or {}
    slopes = {axis: {c: v for c, v in row.items() if c in ANGULAR}
              for axis, row in (off_axis.get("slopes") or {}).items() if axis in LINEAR}
    if not any(slopes.values()) or not positions:
        return None, None
    labels = list(positions)
    errors = np.array([off_axis_error(slopes, positions[label]) for label in labels])
    u = np.concatenate([np.zeros(3), np.sqrt(np.mean(errors[:, 3:] ** 2, axis=0))])
    term = BudgetTerm("off-axis angle error", "the angles' cross-axis error left by the per-component compensation: "
                      "the displacement calibration's slopes of a, b, c along the x, y, z lines, at the run's points",
                      Correlation.POINT, tuple(float(v) for v in u))
    summary = {"slopes_rad_per_m": slopes,
               "at_points": {label: dict(zip(ANGULAR, e[3:].tolist())) for label, e in zip(labels, errors)},
               "standard_uncertainty": dict(zip(COMPONENTS, u.tolist()))}
    return term, summary


def squareness_terms(squareness: float, positions: Mapping[str, Sequence[float]], lever: float,
                     transform: bool) -> list[BudgetTerm]:
    """The instrument's position frame against its angle frame (rotation) and its axes' squareness (shear).

    Neither calibration measures them: the displacement calibration scales each axis along the robot's
    lines, whose direction in M it cannot know, and the angle calibration turns about M's axes at its
    origin. Given a standard uncertainty ``squareness`` (rad, the station's or the operator's statement),
    the rotation moves the orientation the transform fit finds (a run term on a, b, c, and on the tool
    point at ``lever``) and the shear the points' positions (a point term, u = squareness × the points'
    RMS distance from their centroid).
    """
    if squareness <= 0:
        return []
    points = np.array([p[:3] for p in positions.values()], dtype=float)
    spread = float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1)))) if len(points) else 0.0
    source = f"stated frame squareness {squareness:.3g} rad (not calibrated by the per-axis method)"
    terms = [BudgetTerm("frame shear", source, Correlation.POINT, (squareness * spread,) * 3 + (0.0,) * 3)]
    position = squareness * lever if transform else 0.0  # the fit's rotation moves the commanded tool point
    terms.append(BudgetTerm("frame rotation", source, Correlation.RUN, (position,) * 3 + (squareness,) * 3))
    return terms


def environment_scale_term(run_air_k: float | None, calibration_air_k: float | None) -> BudgetTerm:
    """The instrument's thermal scale between its calibration and this run (a relative error)."""
    if run_air_k is None or calibration_air_k is None:
        u = INSTRUMENT_EXPANSION_PER_K * UNKNOWN_TEMPERATURE_HALF_WIDTH_K / math.sqrt(3.0)
        source = ("air temperature not recorded for the run or the calibration: "
                  f"±{UNKNOWN_TEMPERATURE_HALF_WIDTH_K:g} K assumed, α = {INSTRUMENT_EXPANSION_PER_K:g} /K")
    else:
        delta = run_air_k - calibration_air_k
        u = INSTRUMENT_EXPANSION_PER_K * math.sqrt(delta**2 / 3.0 + 2 * AIR_SENSOR_UNCERTAINTY_K**2)
        source = (f"ΔT = {delta:.3g} K between the run and the calibration (environmental unit), "
                  f"α = {INSTRUMENT_EXPANSION_PER_K:g} /K (the screens' frame)")
    return BudgetTerm("environment", source, Correlation.SCALE, (u, u, u, 0.0, 0.0, 0.0),
                      distribution=Distribution.RECTANGULAR, shared=True)


def iso_budget(infos: Sequence[Mapping[str, Any]], applied: set[str], *, frames_per_pose: int,
               per_frame: Sequence[Sequence[Sequence[float]]] | None, transform: Mapping[str, Any] | None,
               run_air_k: float | None, positions: Mapping[str, Sequence[float]], squareness: float = 0.0
               ) -> tuple[UncertaintyBudget, dict[str, Any], dict[str, Any] | None]:
    """The run's budget and the frame-noise estimator's description.

    Parameters
    ----------
    infos : the ``info()`` of every calibration record of the station (applied or not)
    applied : components the records in force corrected in this run
    frames_per_pose : the run's frames per pose
    per_frame : (n_poses, k, 6) per-frame OPR poses of the run, for the cross-check, or None
    transform : ``{"points": n, "spread": ρ, "lever": L}`` of the transform step, or None
    run_air_k : the run's mean air temperature, K, or None
    positions : point → the OPR's measured position (m, in M), for the off-axis error
    squareness : the stated frame squareness (rad, standard uncertainty); 0: not stated, not in U

    Returns
    -------
    The budget, the frame-noise estimator's description, and the off-axis error's (or None).

    Raises
    ------
    BudgetUnavailable
        With the one-line reason.
    """
    sources = component_sources(infos)
    noise, estimator = frame_noise_term(sources, frames_per_pose, per_frame)
    compensation = compensation_residual_term(sources, applied)
    terms = [noise, compensation, *reference_terms(sources)]
    off_axis, off_axis_summary = off_axis_terms(sources, positions)
    if off_axis is not None:
        terms.append(off_axis)
    if transform is not None:
        terms.append(transform_fit_term(noise, compensation, int(transform["points"]), float(transform["spread"]),
                                        float(transform["lever"])))
    terms += squareness_terms(squareness, positions, float((transform or {}).get("lever") or 0.0),
                              transform is not None)
    calibration_c = (sources.get("x") or {}).get("temperature_c")
    calibration_k = None if calibration_c is None else float(calibration_c) + 273.15
    terms.append(environment_scale_term(run_air_k, calibration_k))
    return UncertaintyBudget(tuple(terms)), estimator, off_axis_summary
