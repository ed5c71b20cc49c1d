"""The analysis of the runs measured in motion: per move and per setting, with U and, in simulation,
the same functions applied to the twins' truth (docs/dynamic.md, "Procedures"; docs/results.md).

Measuring point: the tool point (the OPR pose through the station's nominal ``tool_in_opr``, as the
static kind does). "True": the twin's true OPR pose in M at the stream's own instants
(``_dynamic_truth``) through the same nominal tool offset, so measured and true differ only by the
instrument's error; the stabilisation figures are also given from the dense (1 kHz) truth.

Uncertainty (k = 2), what each U holds:

- **stream noise** σ per position component, from the run itself: the MAD of the second differences
  of the settled tail (a smooth motion's second differences are ~0), /√6. In every U.
- **frame period** Δt (rate_hz): the stabilisation instant is interpolated between samples, Δt/√12.
- **compensation residual**: the records' held-out RMS of x, y, z (the largest), in AT_p and CR (figures
  against the commanded path in the measured frame); the static ISO budget's other terms (interferometer
  scale, environment, off-axis angles, frame squareness) and the transform fit's own noise are not carried.
- Not covered: the clock fit (tens of µs: below a frame period), motion blur (the pose at an exposure's
  middle), the circle's chord sag between samples (``chord_sag`` says how large it may be).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from instrument.iso9283 import (
    ISO9283Error,
    circular_path,
    corner_deviation,
    linear_path,
    minimum_positioning_time,
    path_characteristics,
    path_velocity,
    pose_stabilisation,
)
from procedures.kinds._protocol import AnalysisContext
from procedures.kinds._stream import StreamRecord
from procedures.kinds.dynamic._plan import tcp_at
from procedures.kinds.dynamic._truth import MoveTruth
from procedures.station import euler_to_matrix, matrix_to_euler, tcp_in_m, ur_to_matrix
from procedures.store import Sample

SERIES_POINTS = 400  # samples kept per plotted series
DEFAULT_BAND_M = 10e-6


def tool_poses(opr: np.ndarray, opr_to_tool: np.ndarray) -> np.ndarray:
    """(N, 6) tool-point poses in M from (N, 6) OPR poses, with the 4×4 OPR → tool transform."""
    from scipy.spatial.transform import Rotation
    opr = np.asarray(opr, dtype=float).reshape(-1, 6)
    if not len(opr):
        return opr.copy()
    rotations = Rotation.from_euler("xyz", opr[:, 3:])
    positions = opr[:, :3] + rotations.apply(opr_to_tool[:3, 3])
    angles = (rotations * Rotation.from_matrix(opr_to_tool[:3, :3])).as_euler("xyz")
    return np.column_stack([positions, angles])


def noise_sigma(positions: np.ndarray) -> float:
    """σ (m) of one position component's white noise, from second differences (robust: MAD)."""
    positions = np.asarray(positions, dtype=float)
    if len(positions) < 5:
        return float("nan")
    positions = positions.reshape(len(positions), -1)
    second = np.diff(positions, n=2, axis=0)
    mad = np.median(np.abs(second - np.median(second, axis=0)), axis=0) * 1.4826
    return float(np.sqrt(np.mean(mad**2)) / math.sqrt(6.0))


def rest_noise(record: StreamRecord, tool: np.ndarray, settle_s: float = 0.1) -> float:
    """σ of the stream's noise from the samples after the done signal (+ ``settle_s``): the robot
    at rest there, so the second differences are noise (a moving path's are its curvature)."""
    signal = record.meta.get("t_signal")
    if signal is None:
        return float("nan")
    return noise_sigma(tool[record.t >= float(signal) + settle_s, :3])


def _finite(value: Any) -> float | None:
    return None if value is None or not math.isfinite(float(value)) else float(value)


def _series(t: np.ndarray, values: np.ndarray, origin: float) -> dict[str, list[float]]:
    step = max(1, len(t) // SERIES_POINTS)
    return {"t": (t[::step] - origin).tolist(), "value": values[::step].tolist()}


def compensation_position_rms(ctx: AnalysisContext) -> float | None:
    """The largest held-out RMS of x, y, z among the records in force (None: no record covers them)."""
    found = []
    for compensator in ctx.compensators:
        evaluation = (compensator.info() or {}).get("evaluation") or {}
        found += [float(e["heldout_rms"]) for c, e in evaluation.items() if c in "xyz" and e.get("heldout_rms")]
    return max(found) if found else None


def streams_of(ctx: AnalysisContext, samples: Sequence[Sample]) -> dict[int, StreamRecord]:
    if ctx.streams is None:
        return {}
    wanted = [s.step_index for s in samples if s.ok]
    return {k: StreamRecord.from_stored(v) for k, v in ctx.streams(wanted).items()}


def truth_for(truths: Mapping[str, MoveTruth], record: StreamRecord) -> MoveTruth | None:
    path = record.meta.get("truth_log")
    return truths.get(str(path)) if path else None


# ----------------------------------------------------------------------------- stabilisation
def stabilisation_move(record: StreamRecord, opr_to_tool: np.ndarray, band: float,
                       truth: MoveTruth | None) -> dict[str, Any]:
    """One arrival's figures (ISO 9283 7.4, 7.5) with U, and the truth's."""
    tool = tool_poses(record.pose, opr_to_tool)
    signal = float(record.meta["t_signal"])
    result = pose_stabilisation(record.t, tool[:, :3], signal, band)
    period = 1.0 / float(record.meta.get("rate_hz") or 1.0)
    tail = tool[record.t >= record.t[-1] - 0.3 * (record.t[-1] - signal), :3]
    sigma = noise_sigma(tail)
    n_tail = max(3, len(tail))
    u_overshoot = 2.0 * sigma * math.sqrt(1.0 + 1.0 / n_tail)
    u_time = None
    if math.isfinite(result.stabilisation_time) and result.stabilisation_time > 0:
        k = int(np.searchsorted(record.t, result.settled_time))
        k = min(max(k, 1), len(record.t) - 1)
        slope = abs(result.distance[k] - result.distance[k - 1]) / max(record.t[k] - record.t[k - 1], 1e-9)
        u_time = 2.0 * math.sqrt(period**2 / 12.0 + (sigma / max(slope, 1e-9)) ** 2)
    move: dict[str, Any] = {
        "t_signal": signal, "stabilisation_time": _finite(result.stabilisation_time),
        "overshoot": float(result.overshoot),
        "u_stabilisation_time": u_time, "u_overshoot": u_overshoot if math.isfinite(u_overshoot) else None,
        "settled_time": _finite(result.settled_time), "attained": result.attained.tolist(), "noise_sigma": sigma,
        "poses": len(record), "dropped": record.dropped, "frame_period": period,
        "series": _series(record.t, result.distance, signal),
    }
    if truth is not None:
        true_tool = tool_poses(truth.opr_in_m(record.t), opr_to_tool)
        same = pose_stabilisation(record.t, true_tool[:, :3], signal, band)
        times, dense = truth.dense(float(record.t[0]), float(record.t[-1]))
        true_dense = None
        if len(times) > 10 and times[0] <= signal <= times[-1]:
            dense_result = pose_stabilisation(times, tool_poses(dense, opr_to_tool)[:, :3], signal, band)
            true_dense = {"stabilisation_time": _finite(dense_result.stabilisation_time),
                          "overshoot": float(dense_result.overshoot)}
        move["true"] = {"stabilisation_time": _finite(same.stabilisation_time), "overshoot": float(same.overshoot),
                        "series": _series(record.t, same.distance, signal), "dense": true_dense}
    return move


def positioning_times(records: Mapping[str, Sequence[StreamRecord]], opr_to_tool: np.ndarray,
                      band: float) -> dict[str, Any] | None:
    """ISO 9283 9 from the streamed moves, per speed setting (None when it cannot be evaluated)."""
    settings = {label: [(r.t, tool_poses(r.pose, opr_to_tool)[:, :3]) for r in moves]
                for label, moves in records.items() if moves}
    if not settings:
        return None
    try:
        result = minimum_positioning_time(settings, band)
    except (ISO9283Error, ValueError) as exc:
        return {"error": str(exc)}
    return {"minimum": _finite(result.minimum), "setting": result.setting,
            "per_setting": {k: _finite(v) for k, v in result.per_setting.items()}}


def band_of(params: Any, ctx_station: Any) -> tuple[float, str]:
    """The stabilisation band (m) and where it came from."""
    if params.band_um is not None:
        return float(params.band_um) * 1e-6, "parameter band_um"
    rated = ctx_station.rated
    if rated is not None and rated.stabilisation_band is not None:
        return float(rated.stabilisation_band), "station rated.stabilisation_band"
    return DEFAULT_BAND_M, "assumed (neither band_um nor the station's rated.stabilisation_band is given)"


def summarise(moves: Sequence[Mapping[str, Any]], key: str) -> dict[str, Any]:
    """Mean and largest of a per-move figure over the cycles, with the largest U among them."""
    values = [m[key] for m in moves if m.get(key) is not None]
    us = [m[f"u_{key}"] for m in moves if m.get(f"u_{key}") is not None]
    true_values = [m["true"][key] for m in moves if m.get("true") and m["true"].get(key) is not None]
    return {"mean": float(np.mean(values)) if values else None, "max": float(np.max(values)) if values else None,
            "n": len(values), "never_settled": sum(1 for m in moves if m.get(key) is None),
            "expanded_uncertainty": float(np.max(us)) if us else None,
            "true_mean": float(np.mean(true_values)) if true_values else None,
            "true_max": float(np.max(true_values)) if true_values else None}


# --------------------------------------------------------------------------------------- paths
def fitted_frame(ctx: AnalysisContext, samples: Sequence[Sample], truths: Mapping[str, MoveTruth]
                 ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """The robot↔M transform from the transform pass (as the static kind), and the truth's frame
    carried onto it ("mirror"); identity when the pass has fewer than 3 poses."""
    reference = ctx.station.frames.reference_tcp_pose
    mine = [s for s in samples if s.phase == "transform" and s.ok]
    if len(mine) < 3:
        return np.eye(4), np.eye(4), {"fitted": False}
    source = np.array([tcp_in_m(reference, s.robot_target())[:3, 3] for s in mine])
    target = np.array([np.asarray(s.measured_pose())[:3] for s in mine])
    rotation, translation, rms = ctx.science.fit_rigid_transform(source, target)
    fitted = np.eye(4)
    fitted[:3, :3], fitted[:3, 3] = rotation, translation
    mirror = np.eye(4)
    if ctx.truth is not None:
        true = [ctx.truth.at(s.t_measured) if s.t_measured is not None else None for s in mine]
        if all(t is not None and "opr_in_m" in t for t in true):
            true_positions = np.array([t["opr_in_m"]["t"] for t in true if t is not None])
            r2, t2, _ = ctx.science.fit_rigid_transform(source, true_positions)
            true_fit = np.eye(4)
            true_fit[:3, :3], true_fit[:3, 3] = r2, t2
            mirror = fitted @ np.linalg.inv(true_fit)
    return fitted, mirror, {"fitted": True, "residual_rms": float(rms), "points": len(mine),
                            "rotation": rotation.tolist(), "translation": translation.tolist()}


def commanded_tool(ctx: AnalysisContext, fitted: np.ndarray, point_in_m: Sequence[float] | np.ndarray
                   ) -> np.ndarray:
    """(6,) the commanded tool pose for an OPR point in nominal M, in the measured frame."""
    reference = ctx.station.frames.reference_tcp_pose
    opr_to_tool = ur_to_matrix(ctx.station.frames.tool_in_opr)
    return matrix_to_euler(fitted @ tcp_in_m(reference, tcp_at(ctx.station, point_in_m)) @ opr_to_tool)


def true_tool_path(record: StreamRecord, truth: MoveTruth | None, mirror: np.ndarray,
                   opr_to_tool: np.ndarray) -> np.ndarray | None:
    """The true tool poses at the stream's instants, in the measured frame."""
    if truth is None:
        return None
    opr = truth.opr_in_m(record.t)
    return np.array([matrix_to_euler(mirror @ euler_to_matrix(p) @ opr_to_tool) for p in opr])


def path_figures(command: Any, measured: Sequence[np.ndarray], true: Sequence[np.ndarray] | None,
                 u_position: Callable[[int], float | None]) -> dict[str, Any]:
    """AT/RT (position and orientation) of one commanded path, measured and true, with U(AT_p)."""
    out: dict[str, Any] = {}
    try:
        m = path_characteristics(command, list(measured))
    except ISO9283Error as exc:
        return {"error": str(exc)}
    out.update({k: float(getattr(m, k)) for k in ("at_p", "at_a", "at_b", "at_c", "rt_p", "rt_a", "rt_b", "rt_c")})
    out["u_at_p"] = u_position(len(measured))
    out["deviation"] = m.deviation.tolist()
    out["rt_l"] = m.rt_l.tolist()
    if true:
        try:
            tr = path_characteristics(command, list(true))
            out["true"] = {k: float(getattr(tr, k)) for k in ("at_p", "at_a", "at_b", "at_c", "rt_p", "rt_a", "rt_b",
                                                              "rt_c")}
            out["true"]["deviation"] = tr.deviation.tolist()
        except ISO9283Error as exc:
            out["true"] = {"error": str(exc)}
    return out


def linear_command(a: np.ndarray, b: np.ndarray, points: int) -> Any:
    return linear_path(a[:3], b[:3], points=points, orientation=a[3:], margin=0.1)


def circle_command(centre: np.ndarray, start: np.ndarray, via: np.ndarray, points: int) -> tuple[Any, float]:
    radius = float(np.linalg.norm(start[:3] - centre[:3]))
    normal = np.cross(start[:3] - centre[:3], via[:3] - centre[:3])
    return circular_path(centre[:3], radius, normal, start[:3] - centre[:3], points=points, sweep=2 * np.pi * 0.9,
                         orientation=centre[3:]), radius


def corner_figures(corner: np.ndarray, before: np.ndarray, after: np.ndarray, measured: Sequence[np.ndarray],
                   true: Sequence[np.ndarray] | None, u_position: float | None, sigma: float) -> dict[str, Any]:
    try:
        m = corner_deviation(corner[:3], corner[:3] - before[:3], after[:3] - corner[:3],
                             [p[:, :3] for p in measured])
    except ISO9283Error as exc:
        return {"error": str(exc)}
    out: dict[str, Any] = {"cr": float(m.cr), "co": float(m.co), "cr_cycles": m.cr_cycles.tolist(),
                           "co_cycles": m.co_cycles.tolist(), "u_cr": u_position,
                           "u_co": 2.0 * sigma if math.isfinite(sigma) else None}
    if true:
        tr = corner_deviation(corner[:3], corner[:3] - before[:3], after[:3] - corner[:3], [p[:, :3] for p in true])
        out["true"] = {"cr": float(tr.cr), "co": float(tr.co)}
    return out


def middle_of_leg(t: np.ndarray, positions: np.ndarray, a: np.ndarray, b: np.ndarray,
                  lo: float = 0.25, hi: float = 0.75) -> tuple[np.ndarray, np.ndarray]:
    """The samples whose projection on the leg a → b lies in [lo, hi] of its length (constant speed)."""
    direction = b[:3] - a[:3]
    length = float(np.linalg.norm(direction))
    along = (positions[:, :3] - a[:3]) @ (direction / length) / length
    inside = (along >= lo) & (along <= hi)
    return t[inside], positions[inside, :3]


def velocity_figures(cycles: Sequence[tuple[np.ndarray, np.ndarray]], commanded: float, sigma: float,
                     true_cycles: Sequence[tuple[np.ndarray, np.ndarray]] | None) -> dict[str, Any]:
    usable = [(t, p) for t, p in cycles if len(t) >= 5]
    if len(usable) < 2:
        return {"error": "fewer than 2 cycles with ≥ 5 poses on the constant-speed part of the leg"}
    try:
        m = path_velocity(usable, commanded)
    except ISO9283Error as exc:
        return {"error": str(exc)}
    period = float(np.median(np.diff(usable[0][0])))
    sigma_v = math.sqrt(2.0) * sigma / period if math.isfinite(sigma) and period > 0 else float("nan")
    n = sum(len(t) for t, _ in usable)
    out: dict[str, Any] = {"av": float(m.av), "rv": float(m.rv), "fv": float(m.fv), "mean_speed": float(m.mean_speed),
                           "commanded": commanded,
                           "u_av": 2.0 * sigma_v / (commanded * math.sqrt(n)) if math.isfinite(sigma_v) else None,
                           "u_fv": 2.0 * math.sqrt(2.0) * sigma_v if math.isfinite(sigma_v) else None}
    if true_cycles:
        try:
            tr = path_velocity([(t, p) for t, p in true_cycles if len(t) >= 5], commanded)
            out["true"] = {"av": float(tr.av), "rv": float(tr.rv), "fv": float(tr.fv)}
        except ISO9283Error as exc:
            out["true"] = {"error": str(exc)}
    return out
