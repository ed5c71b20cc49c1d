"""One self-contained HTML report per run, and CSV / JSON exports. Units are converted here only."""

from __future__ import annotations

import csv
import io
import json
import time
from html import escape
from typing import Any

import numpy as np

from procedures._svg import scatter

ARCSEC = np.pi / (180 * 3600)
LINEAR = ("x", "y", "z")
_CSS = """body{font-family:sans-serif;margin:2em;max-width:1100px;color:#222}
table{border-collapse:collapse;margin:1em 0}th,td{border:1px solid #bbb;padding:3px 8px;text-align:right}
th{background:#eee}td.l,th.l{text-align:left}.true{color:#2a7a2a}.bad{color:#b00}
pre{background:#f6f6f6;padding:8px;overflow-x:auto;font-size:11px}.plots svg{margin:4px}"""


def _fmt(value: Any, scale: float, digits: int = 2) -> str:
    if value is None or not isinstance(value, (int, float)) or not np.isfinite(value):
        return "—"
    return f"{value * scale:.{digits}f}"


def _ci(stats: dict, key: str, scale: float, digits: int) -> str:
    ci = stats.get(f"{key}_ci")
    if isinstance(stats.get("ci"), dict):
        ci = ci or stats["ci"].get(key)
    if isinstance(ci, (list, tuple)) and len(ci) == 2:
        return f" <small>[{_fmt(ci[0], scale, digits)}, {_fmt(ci[1], scale, digits)}]</small>"
    return ""


def _time(stamp: float | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(stamp)) if stamp else "—"


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


def _iso_section(results: dict) -> str:
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
        cells = "".join(f"<td>{_fmt(stats.get(k), s, d)}{_ci(stats, k, s, d)}</td>" for k, _, s, d in ISO_COLUMNS)
        rows.append(f"<tr><td class=l>{escape(label)}</td><td>{entry['n']}</td>{cells}</tr>")
        if "true_stats" in entry:
            true = entry["true_stats"]
            cells = "".join(f"<td class=true>{_fmt(true.get(k), s, d)}</td>" for k, _, s, d in ISO_COLUMNS)
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
            f"residual RMS {_fmt(transform.get('residual_rms'), 1e6)} µm.</p>"
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


def _calibration_section(results: dict) -> str:
    rows, plots = [], []
    for name, curve in (results.get("curves") or {}).items():
        unit, scale, eunit, escale = _component_units(name)
        measured = np.asarray(curve.get("measured", []), float)
        before = np.asarray(curve.get("error_before", []), float)
        after = np.asarray(curve.get("error_after", []), float) if curve.get("error_after") is not None else None
        def stat(a, escale=escale):
            return (
                (f"{np.max(np.abs(a)) * escale:.3f}", f"{np.sqrt(np.mean(a**2)) * escale:.3f}")
                if a is not None and a.size
                else ("—", "—")
            )

        b, a = stat(before), stat(after)
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


def render_report(run: dict, samples: list, events: list[dict]) -> str:
    """The whole report as one HTML string (inline CSS and SVG, no external resources)."""
    results = run.get("results") or {}
    ok = sum(1 for s in samples if s.ok)
    header = (f"<h1>{escape(run.get('procedure_name') or run['procedure'])}</h1><table>"
              + "".join(f"<tr><th class=l>{k}</th><td class=l>{v}</td></tr>" for k, v in (
                  ("run", f"<code>{run['id']}</code>"), ("procedure", escape(run["procedure"])),
                  ("state", f"{run['state']} ({escape(str(run.get('exit_status') or ''))})"),
                  ("reason", escape(str(run.get("reason") or ""))),
                  ("station", escape(f"{run.get('station_name')} — {run.get('station_path')}")),
                  ("calibration record", escape(str(run.get("calibration_record_id") or "none"))),
                  ("software", escape(str(run.get("software_version")))),
                  ("created / started / finished", f"{_time(run['created'])} / {_time(run.get('started'))} / "
                                                   f"{_time(run.get('finished'))}"),
                  ("samples", f"{ok} measured, {len(samples) - ok} failed, of {run.get('total_steps')} planned"),
              )) + "</table>")
    if results.get("kind") == "iso9283":
        body = _iso_section(results)
    elif results.get("kind", "").endswith("_calibration"):
        body = _calibration_section(results)
    else:
        body = "<p>No results: the run has not finished.</p>"
    failed = [s for s in samples if not s.ok]
    failed_html = (
        (
            "<h2>Failed poses</h2><table><tr><th class=l>step</th><th class=l>error</th><th class=l>frames</th></tr>"
            + "".join(
                f"<tr><td class=l>{escape(s.step_key)}</td><td class=l>{escape(s.error or '')}</td>"
                f"<td class=l>{len(s.frames or [])} saved</td></tr>"
                for s in failed
            )
            + "</table>"
        )
        if failed
        else ""
    )
    event_rows = "".join(f"<tr><td class=l>{_time(e['time'])}</td><td class=l>{escape(e['kind'])}</td>"
                         f"<td class=l>{escape(e['message'] or '')}</td></tr>" for e in events
                         if e["kind"] not in ("measure_failed",))
    provenance = (
        f"<h2>Provenance</h2><h3>Parameters</h3><pre>{escape(json.dumps(run.get('parameters'), indent=1))}</pre>"
        f"<h3>Procedure file</h3><pre>{escape(run.get('procedure_text') or '')}</pre>"
        f"<h3>Station snapshot</h3><pre>{escape(json.dumps(run.get('station'), indent=1))}</pre>"
        f"<h3>Events</h3><table>{event_rows}</table>"
    )
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>run {run['id'][:8]} — {escape(run['procedure'])}"
            f"</title><style>{_CSS}</style></head><body>{header}{body}{failed_html}{provenance}</body></html>")


SAMPLE_COLUMNS = (
    ["run_id", "step_index", "step_key", "phase", "label", "ok", "error"]
    + [f"commanded_tcp_{k}" for k in ("x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad")]
    + [f"solved_{k}" for k in ("x_m", "y_m", "z_m", "alpha_rad", "theta_rad", "gamma_rad")]
    + [f"corrected_{k}" for k in ("x_m", "y_m", "z_m", "alpha_rad", "theta_rad", "gamma_rad")]
    + ["residual_rms_m", "reference_value", "interferometer_m", "table_rad", "t_start", "t_measured", "t_committed"]
)


def export_csv(samples: list) -> str:
    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow(SAMPLE_COLUMNS)
    for s in samples:
        commanded = (s.commanded or {}).get("tcp_pose") or [None] * 6
        solved = (s.solved or {}).get("pose") or [None] * 6
        corrected = (s.corrected or {}).get("pose") or [None] * 6
        ref = s.reference or {}
        writer.writerow([s.run_id, s.step_index, s.step_key, s.phase, s.label, int(s.ok), s.error or "",
                         *commanded, *solved, *corrected, (s.solved or {}).get("residual_rms"), ref.get("value"),
                         ref.get("interferometer_m"), ref.get("table_rad"), s.t_start, s.t_measured, s.t_committed])
    return out.getvalue()


def export_json(run: dict, samples: list, events: list[dict]) -> str:
    from dataclasses import asdict

    return json.dumps({"run": run, "samples": [asdict(s) for s in samples], "events": events}, indent=1, default=str)
