"""The dynamic figures in the export's shape: ``{value, expanded_uncertainty, coverage_factor, true, unit}``
per figure (SI), per setting (docs/results.md, "Runs measured in motion")."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

DYNAMIC_KINDS = ("iso9283_stabilisation", "iso9283_path")


def _figure(value: Any, u: Any, true: Any, unit: str) -> dict[str, Any]:
    return {"value": value, "expanded_uncertainty": u, "coverage_factor": 2.0 if u is not None else None,
            "true": true, "unit": unit}


def dynamic_figures(results: Mapping[str, Any]) -> list[dict[str, Any]]:
    """One entry per setting (point and speed, or speed) with its figures."""
    out: list[dict[str, Any]] = []
    if results.get("kind") == "iso9283_stabilisation":
        for s in results.get("settings") or []:
            st, os_ = s["stabilisation_time"], s["overshoot"]
            out.append({"point": s["point"], "speed_percent": s["speed_percent"], "speed": s.get("speed"),
                        "cycles": s["cycles"], "figures": {
                            "stabilisation_time": _figure(st.get("mean"), st.get("expanded_uncertainty"),
                                                          st.get("true_mean"), "s"),
                            "stabilisation_time_max": _figure(st.get("max"), None, st.get("true_max"), "s"),
                            "overshoot": _figure(os_.get("mean"), os_.get("expanded_uncertainty"),
                                                 os_.get("true_mean"), "m"),
                            "overshoot_max": _figure(os_.get("max"), None, os_.get("true_max"), "m")}})
        return out
    for s in results.get("settings") or []:
        figures: dict[str, Any] = {}
        for part in ("leg_1", "leg_2", "circle"):
            f = s.get(part) or {}
            if not f or "error" in f:
                continue
            true = f.get("true") or {}
            figures[f"{part}.at_p"] = _figure(f.get("at_p"), f.get("u_at_p"), true.get("at_p"), "m")
            figures[f"{part}.rt_p"] = _figure(f.get("rt_p"), None, true.get("rt_p"), "m")
            for angle in ("at_a", "at_b", "at_c", "rt_a", "rt_b", "rt_c"):
                figures[f"{part}.{angle}"] = _figure(f.get(angle), None, true.get(angle), "rad")
        corner = s.get("corner") or {}
        if corner and "error" not in corner:
            true = corner.get("true") or {}
            figures["cr"] = _figure(corner.get("cr"), corner.get("u_cr"), true.get("cr"), "m")
            figures["co"] = _figure(corner.get("co"), corner.get("u_co"), true.get("co"), "m")
        velocity = s.get("velocity") or {}
        if velocity and "error" not in velocity:
            true = velocity.get("true") or {}
            figures["av"] = _figure(velocity.get("av"), velocity.get("u_av"), true.get("av"), "1")
            figures["rv"] = _figure(velocity.get("rv"), None, true.get("rv"), "1")
            figures["fv"] = _figure(velocity.get("fv"), velocity.get("u_fv"), true.get("fv"), "m/s")
        out.append({"speed_percent": s["speed_percent"], "speed": s.get("speed"), "figures": figures})
    return out
