"""The results sections of run reports (HTML building blocks the procedure kinds use).

Values are stored in SI; these functions convert to the report's units (µm, °, ″) and say so in
every header.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from html import escape
from typing import Any

import numpy as np

from procedures._svg import scatter

ARCSEC = np.pi / (180 * 3600)
LINEAR = ("x", "y", "z")


def fmt(value: Any, scale: float, digits: int = 2) -> str:
    """``value × scale`` with ``digits`` decimals, or a dash for a missing or non-finite value."""
    if value is None or not isinstance(value, (int, float)) or not np.isfinite(value):
        return "—"
    return f"{value * scale:.{digits}f}"


def _ci(stats: Mapping[str, Any], key: str, scale: float, digits: int) -> str:
    ci = stats.get(f"{key}_ci")
    if isinstance(stats.get("ci"), dict):
        ci = ci or stats["ci"].get(key)
    if isinstance(ci, (list, tuple)) and len(ci) == 2:
        return f" <small>[{fmt(ci[0], scale, digits)}, {fmt(ci[1], scale, digits)}]</small>"
    return ""


# (key, header, scale, digits): RP_l and AP_P in µm, orientation figures in degrees (as the paper's Table 1)
ISO_COLUMNS = (
    ("rp_l", "RP<sub>l</sub> (µm)", 1e6, 2),
    ("rp_a", "RP<sub>a</sub> (°)", 180 / np.pi, 5),
    ("rp_b", "RP<sub>b</sub> (°)", 180 / np.pi, 5),
    ("rp_c", "RP<sub>c</sub> (°)", 180 / np.pi, 5),
    ("ap_p", "AP<sub>P</sub> (µm)", 1e6, 2),
    ("ap_a", "AP<sub>a</sub> (°)", 180 / np.pi, 5),
    ("ap_b", "AP<sub>b</sub> (°)", 180 / np.pi, 5),
    ("ap_c", "AP<sub>c</sub> (°)", 180 / np.pi, 5),
)


def iso_results_html(results: Mapping[str, Any]) -> str:
    """ISO 9283 figures per point (measured, and true in simulation), transform step, attained-pose plots."""
    points = results.get("points", {})
    has_truth = any("true_stats" in p for p in points.values())
    head = "".join(f"<th>{h}</th>" for _, h, _, _ in ISO_COLUMNS)
    rows = []
    for label in results.get("order", []):
        entry = points[label]
        if "stats" not in entry:
            rows.append(f"<tr><td class=l>{escape(label)}</td><td>{entry.get('n', 0)}</td>"
                        f"<td class='l bad' colspan={len(ISO_COLUMNS)}>{escape(entry.get('error', ''))}</td></tr>")
            continue
        stats = entry["stats"]
        cells = "".join(f"<td>{fmt(stats.get(k), s, d)}{_ci(stats, k, s, d)}</td>" for k, _, s, d in ISO_COLUMNS)
        rows.append(f"<tr><td class=l>{escape(label)}</td><td>{entry['n']}</td>{cells}</tr>")
        if "true_stats" in entry:
            true = entry["true_stats"]
            cells = "".join(f"<td class=true>{fmt(true.get(k), s, d)}</td>" for k, _, s, d in ISO_COLUMNS)
            rows.append(
                f"<tr><td class='l true'>{escape(label)} (true)</td><td class=true>{true.get('n', '')}</td>{cells}</tr>"
            )
    note = ("<p>Rows marked <span class=true>(true)</span> are computed from the simulated cell's ground-truth "
            "log at the same instants. Their RP columns compare like for like with the measured rows. Their AP "
            "columns do not: they put the true tool point, which carries the OPR and tool mounting errors the "
            "simulated cell hides from the instrument, against the commanded poses of the measured transform "
            "step.</p>") if has_truth else ""
    transform = results.get("transform", {})
    transform_text = (
        (
            f"<p>End-effector transform step: robot↔M rigid fit over {transform.get('points')} poses, "
            f"residual RMS {fmt(transform.get('residual_rms'), 1e6)} µm.</p>"
        )
        if transform.get("fitted")
        else "<p>No end-effector transform step (commanded poses used as they are).</p>"
    )
    comp = results.get("compensation") or []
    comp_text = (
        f"<p>Compensation applied: {escape(', '.join(comp))}.</p>" if comp else "<p>No compensation applied.</p>"
    )
    plots = []
    for label in results.get("order", []):
        entry = points[label]
        if "poses" not in entry:
            continue
        poses = np.asarray(entry["poses"]) * 1e6
        centre = poses.mean(axis=0)
        series = [("measured", poses[:, 0] - centre[0], poses[:, 1] - centre[1])]
        if "true_poses" in entry:
            true = np.asarray(entry["true_poses"]) * 1e6
            tc = true.mean(axis=0)
            series.append(("true", true[:, 0] - tc[0], true[:, 1] - tc[1]))
        plots.append(scatter(series, title=f"{label}: attained positions about the barycentre",
                             xlabel="x − x̄ (µm)", ylabel="y − ȳ (µm)", square=True))
        series = [("measured", poses[:, 0] - centre[0], poses[:, 2] - centre[2])]
        plots.append(scatter(series, title=f"{label}: x–z", xlabel="x − x̄ (µm)", ylabel="z − z̄ (µm)", square=True))
    return (f"<h2>ISO 9283 pose repeatability and accuracy</h2>{transform_text}{comp_text}"
            f"<table><tr><th class=l>point</th><th>n</th>{head}</tr>{''.join(rows)}</table>"
            "<p>RP<sub>l</sub> = l̄ + 3·S<sub>l</sub>; RP<sub>a,b,c</sub> = ±3·S; AP against the commanded pose "
            "(after the transform step). Brackets: confidence interval where the core provides one.</p>"
            f"{note}<h3>Attained poses</h3><div class=plots>{''.join(plots)}</div>")


def _component_units(name: str) -> tuple[str, float, str, float]:
    """(value unit, scale, error unit, scale)."""
    return ("mm", 1e3, "µm", 1e6) if name in LINEAR else ("°", 180 / np.pi, "″", 1 / ARCSEC)


def _max_and_rms(errors: np.ndarray | None, scale: float) -> tuple[str, str]:
    if errors is None or not errors.size:
        return "—", "—"
    return f"{np.max(np.abs(errors)) * scale:.3f}", f"{np.sqrt(np.mean(errors**2)) * scale:.3f}"


def calibration_results_html(results: Mapping[str, Any]) -> str:
    """Errors before and after the fitted record, per component, with plots; reference against truth in simulation."""
    rows, plots = [], []
    for name, curve in (results.get("curves") or {}).items():
        unit, scale, eunit, escale = _component_units(name)
        measured = np.asarray(curve.get("measured", []), float)
        before = np.asarray(curve.get("error_before", []), float)
        after = np.asarray(curve.get("error_after", []), float) if curve.get("error_after") is not None else None
        b, a = _max_and_rms(before, escale), _max_and_rms(after, escale)
        rows.append(f"<tr><td class=l>{name}</td><td>{measured.size}</td><td>{b[0]}</td><td>{b[1]}</td>"
                    f"<td>{a[0]}</td><td>{a[1]}</td></tr>")
        series = [("before", measured * scale, before * escale)]
        if after is not None and after.size:
            series.append(("after", measured * scale, after * escale))
        plots.append(scatter(series, title=f"{name}: error against measured value", xlabel=f"measured {name} ({unit})",
                             ylabel=f"error ({eunit})", zero_line=True))
    data = results.get("data") or {}
    truth_rows = []
    for name, entries in data.items():
        diffs = [e["reference"] - e["true"] for e in entries if "true" in e]
        if diffs:
            _, _, eunit, escale = _component_units(name)
            d = np.asarray(diffs)
            truth_rows.append(f"<tr><td class=l>{name}</td><td>{len(d)}</td><td class=true>{np.mean(d) * escale:.3f}"
                              f"</td><td class=true>{np.std(d) * escale:.3f}</td><td>{eunit}</td></tr>")
    truth = ("<h3>Reference against simulated truth</h3><table><tr><th class=l>component</th><th>n</th>"
             "<th>mean (reference − true)</th><th>std</th><th class=l>unit</th></tr>"
             + "".join(truth_rows) + "</table>") if truth_rows else ""
    summary = results.get("summary") or {}
    return (
        f"<h2>Calibration</h2><p>Record written: <code>{escape(str(results.get('record_path')))}</code>, "
        f"id <code>{escape(str(results.get('record_id')))}</code>.</p>"
        "<table><tr><th class=l>component</th><th>samples</th><th>max |error| before (µm or ″)</th>"
        "<th>RMS before (µm or ″)</th><th>max |error| after (µm or ″)</th><th>RMS after (µm or ″)</th></tr>"
        + "".join(rows)
        + "</table>"
        "<p>Error = measured − reference; “after” as reported by the fit (held-out where the core evaluates so).</p>"
        f"<div class=plots>{''.join(plots)}</div>{truth}"
        + (f"<h3>Fit summary</h3><pre>{escape(json.dumps(summary, indent=1, default=str))}</pre>" if summary else "")
    )
