"""The ISO 9283 test conditions of a run, and its deviations from the standard, as data.

Everything here is computed from what the run recorded (its samples' session records and
environmental readings), the procedure's parameters and the station file; nothing is typed in
by hand. Shapes: docs/results.md ("test_conditions", "deviations").
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from instrument import COMPONENTS
from procedures.kinds.iso._parameters import IsoParameters, cube_path
from procedures.station import StationFile, translated_in_frame, ur_to_matrix

STANDARD = "ISO 9283:1998"
ISO_CYCLES = 30
LARGEST_CUBE_TOLERANCE = 0.99  # an edge within 1 % of the largest counts as the largest


def largest_cube_edge(station: StationFile) -> float:
    """The largest cube with M's orientation that fits in the envelope's box (base frame), m."""
    rotation = ur_to_matrix(station.frames.reference_tcp_pose)[:3, :3]
    box = np.asarray(station.envelope.box_max) - np.asarray(station.envelope.box_min)
    return float(np.min(box / np.abs(rotation).sum(axis=1)))


def _first(sessions: Sequence[Mapping[str, Any]], key: str, good: Any = None) -> Any:
    """The first session's ``key``; with ``good``, the first for which ``good(value)`` holds."""
    values = [s.get(key) for s in sessions if s.get(key) is not None]
    if good is not None:
        values = [v for v in values if good(v)] or values
    return values[0] if values else None


def _percent(value: float | None, rated: float | None) -> float | None:
    return None if value is None or rated is None else 100.0 * value / rated


def test_conditions(params: IsoParameters, station: StationFile, points: Mapping[str, Any],
                    sessions: Sequence[Mapping[str, Any]], environment: Mapping[str, Any] | None,
                    infos: Sequence[Mapping[str, Any]], applied: Sequence[Mapping[str, Any]], *,
                    date: str | None, software_version: str) -> dict[str, Any]:
    """The ``test_conditions`` object of an ISO run (docs/results.md)."""
    rated = station.rated
    speed = station.envelope.max_speed * params.speed_percent / 100.0
    acceleration = station.envelope.max_acceleration * params.acceleration_percent / 100.0
    payload = dict(_first(sessions, "payload") or {"mass_kg": params.payload_mass_kg, "cog_m": None,
                                                   "set_on_robot": False})
    payload["rated_mass_kg"] = None if rated is None else rated.payload
    payload["percent_of_rated"] = _percent(payload.get("mass_kg"), payload["rated_mass_kg"])
    reference = station.frames.reference_tcp_pose
    cube_points = {label: {"in_m": in_m, "in_base": tcp} for label, in_m, tcp in cube_path(params, station)}
    applied_ids = {info.get("id") for info in applied}
    return {
        "standard": STANDARD,
        "date": date,
        "operator": _first(sessions, "operator", lambda o: o.get("name")) or {"name": params.operator,
                                                                             "source": "procedure"},
        "robot": _first(sessions, "robot", lambda r: "error" not in r),
        "payload": payload,
        "motion": {
            "speed_m_s": speed, "acceleration_m_s2": acceleration, "speed_mm_s": speed * 1e3,
            "acceleration_mm_s2": acceleration * 1e3, "speed_percent_of_envelope": params.speed_percent,
            "acceleration_percent_of_envelope": params.acceleration_percent,
            "rated_speed_m_s": None if rated is None else rated.speed,
            "rated_acceleration_m_s2": None if rated is None else rated.acceleration,
            "percent_of_rated_speed": _percent(speed, None if rated is None else rated.speed),
            "percent_of_rated_acceleration": _percent(acceleration, None if rated is None else rated.acceleration),
        },
        "cube": {
            "centre_in_m": [float(v) for v in params.cube_center_m], "edge_m": float(params.cube_edge_m),
            "centre_in_base": [float(v) for v in translated_in_frame(reference, params.cube_center_m)[:3]],
            "largest_edge_m": largest_cube_edge(station), "points": cube_points,
        },
        "cycles": {"planned": params.cycles, "measured": {label: entry.get("n", 0) for label, entry in points.items()}},
        "environment": environment,
        "warm_up": _first(sessions, "warm_up") or {"mode": params.warm_up, "duration_s": params.warm_up_s,
                                                   "ran_s": None, "moves": None},
        "measurement_system": {
            "software_version": software_version, "frames_per_pose": params.frames_per_pose,
            "settle_time_s": params.settle_time_s,
            "calibration_records": [_record_entry(info, info.get("id") in applied_ids) for info in infos],
        },
        "sessions": [dict(s) for s in sessions],
    }


def _record_entry(info: Mapping[str, Any], applied: bool) -> dict[str, Any]:
    return {key: info.get(key) for key in ("id", "path", "components", "methods", "date", "run_id", "validity",
                                           "approach_directions", "bidirectional", "temperature_c")} | {
        "applied": applied}


def _deviation(code: str, severity: str, message: str, **details: Any) -> dict[str, Any]:
    return {"code": code, "severity": severity, "message": message, "details": details}


def deviations_of(params: IsoParameters, conditions: Mapping[str, Any], points: Mapping[str, Any],
                  uncertainty: Mapping[str, Any], infos: Sequence[Mapping[str, Any]],
                  applied: Sequence[Mapping[str, Any]], opr_barycentres: Mapping[str, np.ndarray],
                  transform_fitted: bool) -> list[dict[str, Any]]:
    """Every deviation of the run from ISO 9283's test conditions, and the measurement system's warnings."""
    out: list[dict[str, Any]] = []
    short = {label: entry.get("n", 0) for label, entry in points.items() if entry.get("n", 0) < ISO_CYCLES}
    if short:
        fewest = min(short.values())
        out.append(_deviation("cycles_below_30", "deviation", f"{fewest} cycles measured at "
                              f"{', '.join(sorted(short))} (ISO 9283 asks for {ISO_CYCLES})", measured=short))
    covered = sorted({c for info in applied for c in info.get("components") or []}, key=COMPONENTS.index)
    if not params.apply_compensation:
        out.append(_deviation("no_compensation", "warning", "apply_compensation is false: poses not corrected with "
                              "a calibration record"))
    elif not applied:
        out.append(_deviation("no_compensation", "warning", "apply_compensation is true but the station has no "
                              "calibration record in force: poses not corrected"))
    elif len(covered) < len(COMPONENTS):
        missing = [c for c in COMPONENTS if c not in covered]
        out.append(_deviation("compensation_incomplete", "warning", f"no record in force corrects {', '.join(missing)}",
                              missing=missing))
    out += _validity(applied, opr_barycentres)
    out += _directions(applied, points)
    cube = conditions["cube"]
    if cube["edge_m"] < LARGEST_CUBE_TOLERANCE * cube["largest_edge_m"]:
        out.append(_deviation("cube_not_largest", "deviation", f"cube edge {cube['edge_m'] * 1e3:.4g} mm; the "
                              f"envelope holds {cube['largest_edge_m'] * 1e3:.4g} mm (ISO 9283 tests the largest cube "
                              "of the working space)", edge_m=cube["edge_m"], largest_edge_m=cube["largest_edge_m"]))
    if uncertainty.get("evaluated"):
        if uncertainty.get("frame_squareness_rad") is None:
            out.append(_deviation("frame_squareness_not_stated", "warning", "the instrument's position frame against "
                                  "its angle frame is not calibrated and not stated (frame_squareness_urad): U of AP "
                                  "and AD leaves it out"))
        failing = uncertainty.get("above_25_percent") or []
        if failing:
            counts: dict[str, int] = {}
            for figure in failing:
                counts[figure[2]] = counts.get(figure[2], 0) + 1
            where = ", ".join(f"{name} ×{count}" if count > 1 else name for name, count in sorted(counts.items()))
            out.append(_deviation("uncertainty_above_25_percent", "warning", f"{len(failing)} figure values (of "
                                  f"{len(counts)} figures, over the points and pairs) have U above 25 % of their "
                                  f"value: {where}", figures=failing))
    else:
        out.append(_deviation("uncertainty_not_evaluated", "warning", "measurement uncertainty not evaluated: "
                              f"{uncertainty.get('reason')}"))
    out += _rated(conditions)
    warm = conditions.get("warm_up") or {}
    if not (warm.get("ran_s") or warm.get("duration_s")):
        out.append(_deviation("no_warm_up", "deviation", "no warm-up before the test (ISO 9283 tests a robot at its "
                              "operating temperature): set warm_up_s (declared) or warm_up: run"))
    if conditions.get("environment") is None:
        out.append(_deviation("environment_not_recorded", "deviation", "no environmental reading: the air "
                              "temperature and its drift during the test are not recorded"))
    if conditions.get("robot") is None or "error" in (conditions.get("robot") or {}):
        out.append(_deviation("robot_identity_unknown", "deviation", "the robot controller did not say which "
                              "robot it is", error=(conditions.get("robot") or {}).get("error")))
    if not transform_fitted:
        out.append(_deviation("no_transform_step", "warning", "no end-effector transform step: AP is measured "
                              "against the nominal M, with the calibration's datum offsets in it"))
    return out


def _rated(conditions: Mapping[str, Any]) -> list[dict[str, Any]]:
    out = []
    payload = conditions["payload"]
    if payload.get("mass_kg") is None:
        out.append(_deviation("payload_not_rated", "deviation", "payload not stated (ISO 9283 tests at the rated "
                              "payload): set payload_mass_kg"))
    elif payload.get("rated_mass_kg") is not None and abs(payload["percent_of_rated"] - 100.0) > 0.5:
        out.append(_deviation("payload_not_rated", "deviation", f"payload {payload['mass_kg']:g} kg is "
                              f"{payload['percent_of_rated']:.0f} % of the rated {payload['rated_mass_kg']:g} kg",
                              percent_of_rated=payload["percent_of_rated"]))
    percent = conditions["motion"].get("percent_of_rated_speed")
    if percent is not None and abs(percent - 100.0) > 0.5:
        out.append(_deviation("speed_not_rated", "deviation", f"speed {conditions['motion']['speed_mm_s']:.4g} mm/s "
                              f"is {percent:.0f} % of the rated speed (ISO 9283 tests at 100 %)",
                              percent_of_rated_speed=percent))
    return out


def _validity(applied: Sequence[Mapping[str, Any]], barycentres: Mapping[str, np.ndarray]) -> list[dict[str, Any]]:
    beyond: dict[str, list[str]] = {}
    for info in applied:
        for component, (lo, hi) in (info.get("validity") or {}).items():
            k = COMPONENTS.index(component)
            for label, value in barycentres.items():
                if not lo <= float(value[k]) <= hi:
                    beyond.setdefault(label, []).append(component)
    if not beyond:
        return []
    listed = "; ".join(f"{label}: {', '.join(cs)}" for label, cs in beyond.items())
    return [_deviation("outside_validity", "warning", f"points beyond a calibration record's validity range, the "
                       f"correction extrapolated ({listed})", points=beyond)]


def _directions(applied: Sequence[Mapping[str, Any]], points: Mapping[str, Any]) -> list[dict[str, Any]]:
    uncovered: dict[str, list[str]] = {}
    unrecorded = False
    for info in applied:
        for component, covered in (info.get("approach_directions") or {}).items():
            for label, entry in points.items():
                direction = (entry.get("approach") or {}).get(component)
                if direction is None or direction in covered:
                    continue
                uncovered.setdefault(label, []).append(f"{component}{direction:+d}")
                unrecorded |= not covered
    if not uncovered:
        return []
    listed = "; ".join(f"{label}: {', '.join(cs)}" for label, cs in uncovered.items())
    why = ("the calibration recorded no approach direction" if unrecorded
           else "the calibration approached from one direction only")
    return [_deviation("direction_not_covered", "warning", f"points approached from a side the calibration did not "
                       f"cover ({why}; hysteresis not corrected): {listed}", points=uncovered)]
