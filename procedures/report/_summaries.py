"""A run's key results in a few lines: what ``run``/``resume`` print at the end and ``history`` compares.

ISO 9283 runs: per point n, RP_l, RP_a/b/c, AP_P, each with its expanded uncertainty U when the
results carry one, else with the half-width of its sampling interval (the 95 % confidence interval
of RP_l; the other figures then have none). Calibrations: the held-out (leave-one-point-out)
residual of the method the record kept, per component, beside the noise floor. Everything is read
from the stored results dict; units convert here, at the edge (µm, arc-seconds). Which of these a
run gets is the registry's choice (``_sections``), by the shape of its results.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from instrument import ARCSEC
from procedures.kinds.dynamic import dynamic_figures

FIGURE_COLUMNS = {"rp_l": ("RP_l", "µm", 1e6), "rp_a": ("RP_a", "″", 1 / ARCSEC), "rp_b": ("RP_b", "″", 1 / ARCSEC),
                  "rp_c": ("RP_c", "″", 1 / ARCSEC), "ap_p": ("AP_P", "µm", 1e6)}
"""Per ISO figure a terminal column shows: its name, unit and scale from SI."""


def figure_columns(keys: Sequence[str]) -> tuple[tuple[str, str, str, float], ...]:
    """``(key, name, unit, scale)`` of each figure in ``keys`` (its key upper-cased and SI where none is known)."""
    return tuple((key, *FIGURE_COLUMNS.get(key, (key.upper(), "SI", 1.0))) for key in keys)


ISO_FIGURES = figure_columns(("rp_l", "rp_a", "rp_b", "rp_c", "ap_p"))
"""The columns of the RP/AP table ``run`` and ``resume`` print at the end of an ISO run."""
LINEAR = {"x", "y", "z"}
LOPO = "leave-one-point-out"  # the held-out scheme a record's evaluation is chosen by


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value) if math.isfinite(float(value)) else None


def point_figure(entry: Mapping[str, Any], key: str) -> dict[str, Any] | None:
    """One figure of one ISO point: ``{"value", "u", "u_source", "ci"}`` in SI, or None if absent.

    Accepted shapes (older results and those with uncertainties alike): ``stats[key]`` a number with
    ``stats[key + "_ci"]`` an interval, or an object ``{"value", "expanded_uncertainty",
    "confidence_interval"}``; or such an object under ``entry["figures"][key]`` or
    ``entry["uncertainty"][key]`` (a number there is taken as U). ``u`` is the expanded uncertainty
    (``u_source`` ``"U"``), else the half-width of the confidence interval (``"ci"``), else None.
    """
    stats = entry.get("stats") or {}
    # The figure object first: its value is the one the report states (noise bias corrected, docs/uncertainty.md).
    candidates = [(entry.get("figures") or {}).get(key), stats.get(key)]
    value: float | None = None
    u: float | None = None
    ci = None
    for candidate in candidates:
        if isinstance(candidate, dict):
            value = value if value is not None else _number(candidate.get("value"))
            u = u if u is not None else _number(candidate.get("expanded_uncertainty"))
            ci = ci if ci is not None else candidate.get("confidence_interval")
        elif value is None:
            value = _number(candidate)
    ci = ci if ci is not None else stats.get(f"{key}_ci")
    extra = (entry.get("uncertainty") or {}).get(key)
    if u is None:
        u = _number(extra.get("expanded_uncertainty") if isinstance(extra, dict) else extra)
    if value is None:
        return None
    interval = [float(v) for v in ci] if isinstance(ci, (list, tuple)) and len(ci) == 2 and all(
        _number(v) is not None for v in ci) else None
    source = "U" if u is not None else None
    if u is None and interval is not None:
        u, source = (interval[1] - interval[0]) / 2, "ci"
    return {"value": value, "u": u, "u_source": source, "ci": interval}


def iso_rows(results: Mapping[str, Any], keys: Sequence[str] = tuple(FIGURE_COLUMNS)) -> list[dict[str, Any]]:
    """Per ISO point (in the cycle's order): ``point``, ``n`` and each figure of ``keys`` (``point_figure``)."""
    rows = []
    reported = ((results.get("figures") or {}).get("points") or {})  # issue 13's figure objects, per point
    for label in results.get("order") or []:
        entry = (results.get("points") or {}).get(label) or {}
        if isinstance(reported.get(label), dict):
            entry = {**entry, "figures": {**(entry.get("figures") or {}), **reported[label]}}
        rows.append({"point": label, "n": entry.get("n"), "error": entry.get("error"),
                     **{key: point_figure(entry, key) for key in keys}})
    return rows


def changes(previous: Mapping[str, Any] | None, current: Mapping[str, Any]) -> dict[str, float]:
    """The figures of one point that moved by more than the combined uncertainty: key → Δ (SI)."""
    moved: dict[str, float] = {}
    if previous is None:
        return moved
    for key in current:
        before, now = previous.get(key), current.get(key)
        if not before or not now or before.get("u") is None or now.get("u") is None:
            continue
        delta = now["value"] - before["value"]
        if abs(delta) > math.hypot(before["u"], now["u"]):
            moved[key] = delta
    return moved


def shown(fig: Mapping[str, Any] | None, scale: float, digits: int = 2) -> str:
    """``38.27 ± 1.20`` (U or the interval's half-width), ``38.27`` without one, ``–`` when absent."""
    if fig is None:
        return "–"
    text = f"{fig['value'] * scale:.{digits}f}"
    return text + (f" ± {fig['u'] * scale:.{digits}f}" if fig.get("u") is not None else "")


def iso_table_lines(results: Mapping[str, Any]) -> list[str]:
    """The RP/AP table of an ISO run as aligned text lines (µm and arc-seconds)."""
    rows = iso_rows(results, [key for key, *_ in ISO_FIGURES])
    header = ["point", "n", *[f"{name} ({unit})" for _, name, unit, _ in ISO_FIGURES]]
    body = [[row["point"], str(row["n"] if row["n"] is not None else "–"),
             *[shown(row[key], scale) for key, _, _, scale in ISO_FIGURES]] for row in rows]
    sources = {row[key]["u_source"] for row in rows for key, *_ in ISO_FIGURES if row[key] and row[key]["u_source"]}
    lines = _aligned([header, *body])
    if "U" in sources:
        lines.append("± : expanded uncertainty U (k = 2)")
    elif "ci" in sources:
        lines.append("± : half-width of the 95 % confidence interval (sampling only; no uncertainty in these results)")
    if results.get("compensation") == []:  # measured without a calibration record in force
        lines.append("uncompensated: no calibration record was in force, so these figures carry the instrument's own "
                     "systematic errors (run the calibrations, then measure with their records in force)")
    return lines


def held_out_rows(results: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Per component of a calibration: the held-out (leave-one-point-out) residual of the method the
    record kept (the lowest held-out RMS) and the noise floor, SI."""
    summary = results.get("summary") or {}
    method = summary.get("method")
    rows = [r for r in (summary.get("evaluation") or {}).get("rows") or [] if r.get("scheme") == LOPO]
    found = []
    for component in sorted({r["component"] for r in rows}):
        candidates = [r for r in rows if r["component"] == component]
        kept = method.get(component) if isinstance(method, dict) else method  # else the best held out, as kept
        chosen = [r for r in candidates if r.get("method") == kept] or sorted(candidates, key=_rms_or_inf)
        row = chosen[0]
        found.append({"component": component, "method": row.get("method"), "rms": _number(row.get("rms")),
                      "max_abs": _number(row.get("max_abs")), "noise_floor": _number(row.get("noise_floor")),
                      "n": row.get("n_heldout")})
    return found


def _rms_or_inf(row: Mapping[str, Any]) -> float:
    rms = _number(row.get("rms"))
    return math.inf if rms is None else rms


def calibration_lines(results: Mapping[str, Any]) -> list[str]:
    """Where the record went, and the held-out residual per component (µm or arc-seconds)."""
    lines = [f"record {results.get('record_path')} ({results.get('record_id')})"]
    table = [["component", "method", "held-out RMS", "max", "noise floor", "n"]]
    for row in held_out_rows(results):
        scale, unit = (1e6, "µm") if row["component"] in LINEAR else (1 / ARCSEC, "″")
        cells = ["–" if row[key] is None else f"{row[key] * scale:.3f} {unit}" for key in ("rms", "max_abs",
                                                                                          "noise_floor")]
        table.append([row["component"], str(row["method"]), *cells, str(row["n"] if row["n"] is not None else "–")])
    if len(table) > 1:
        lines += ["held-out (leave-one-point-out) residuals after compensation:", *_aligned(table)]
    return lines


def iso_key_results(results: Mapping[str, Any]) -> dict[str, Any]:
    """An ISO run's key results as JSON (SI): its ``points`` (``iso_rows``)."""
    return {"kind": "iso9283", "points": iso_rows(results, [key for key, *_ in ISO_FIGURES])}


def calibration_key_results(results: Mapping[str, Any]) -> dict[str, Any]:
    """A calibration's key results as JSON (SI): the record and its ``held_out`` rows."""
    return {"kind": results.get("kind"), "record_path": results.get("record_path"),
            "record_id": results.get("record_id"), "held_out": held_out_rows(results)}


def dynamic_key_results(results: Mapping[str, Any]) -> dict[str, Any]:
    """A run measured in motion: its figures per setting, as the export gives them (SI)."""
    return {"kind": results["kind"], "settings": dynamic_figures(results)}


def iso_points(results: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Per ISO point of an ``iso9283`` results dict: ``n`` and every scalar figure and interval of its
    statistics (``rp_l``, ``rp_l_ci``, ``ap_p`` ..., SI), without the pose lists. Where the results carry
    figure objects (docs/results.md) their value replaces the statistic (it is the one the report states:
    noise bias corrected) and ``<figure>_u`` is its expanded uncertainty U (k = 2). What the web view's
    run page and the OPC UA server show of a run's figures."""
    points: dict[str, dict[str, Any]] = {}
    if results.get("kind") != "iso9283":
        return points
    for label in results.get("order", []):
        entry = results["points"].get(label) or {}
        stats = entry.get("stats") or {}
        figures: dict[str, Any] = {"n": entry.get("n")}
        for key, value in stats.items():
            if key in ("barycentre", "commanded"):
                continue
            if isinstance(value, (int, float)) or (isinstance(value, list) and len(value) == 2):
                figures[key] = value
        reported = (((results.get("figures") or {}).get("points") or {}).get(label)) or {}
        for key, figure in reported.items():
            if isinstance(figure, dict) and isinstance(figure.get("value"), (int, float)):
                figures[key] = figure["value"]
                if isinstance(figure.get("expanded_uncertainty"), (int, float)):
                    figures[f"{key}_u"] = figure["expanded_uncertainty"]
        if entry.get("error"):
            figures["error"] = entry["error"]
        points[label] = figures
    return points


def _aligned(rows: list[list[str]]) -> list[str]:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return ["  ".join(cell.rjust(width) if i else cell.ljust(width) for i, (cell, width) in
                      enumerate(zip(row, widths))).rstrip() for row in rows]
