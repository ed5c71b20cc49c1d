"""The calibration results section: errors before and after per group with each group's datum
removed (labelled in-sample or held-out), the held-out evaluation per component
(leave-one-point-out and leave-one-group-out) in µm or ″, the reference against the simulated
truth like with like, and the fit summary as a table.

**The datum.** A group's reference is read from its own zero (the interferometer is zeroed at the
group's first point; each group starts from its own offset), so a group's errors carry a constant
that is not the instrument's error. The results (docs/results.md) store each group's errors and
statistics with the group's own mean error removed; for runs stored before that, the same is
computed here from the stored curves, so old and new runs read alike.
"""

from __future__ import annotations

from collections.abc import Mapping
from html import escape
from typing import Any

import numpy as np

from instrument import COMPONENTS
from procedures.report._format import Figure, Unit, component_unit, figure_cell, fmt, is_number
from procedures.report._svg import scatter

LOPO, LOGO = "leave-one-point-out", "leave-one-group-out"
DEGREE = 57.29577951308232


def _array(value: Any) -> np.ndarray:
    try:
        return np.asarray(value if value is not None else [], float).ravel()
    except (TypeError, ValueError):
        return np.zeros(0)


def _stat(errors: np.ndarray) -> dict[str, Any]:
    finite = errors[np.isfinite(errors)]
    if not finite.size:
        return {"rms": None, "max_abs": None, "n": 0}
    return {"rms": float(np.sqrt(np.mean(finite**2))), "max_abs": float(np.max(np.abs(finite))), "n": int(finite.size)}


def group_centred(values: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """``values`` less their group's mean: the group's datum removed."""
    out = values.astype(float).copy()
    for g in np.unique(groups):
        out[groups == g] -= np.mean(values[groups == g])
    return out


def _datum_removed(curve: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(groups, before, after in-sample) with each group's datum removed: as stored, else computed from the
    stored errors the way the analysis does (docs/results.md); None if the curve has no errors."""
    groups = _array(curve.get("group"))
    before, after = _array(curve.get("error_before_datum_removed")), _array(curve.get("error_after_datum_removed"))
    if not before.size or after.size != before.size:
        raw_before, raw_after = _array(curve.get("error_before")), _array(curve.get("error_after"))
        if not raw_before.size or raw_after.size != raw_before.size:
            return None
        if groups.size != raw_before.size:
            groups = np.zeros(raw_before.size)
        before, after = group_centred(raw_before, groups), group_centred(raw_after, groups)
    if groups.size != before.size:
        groups = np.zeros(before.size)
    return groups, before, after


def before_after(results: Mapping[str, Any]) -> dict[str, Any]:
    """Per component, per group and over all groups, the error statistics with each group's datum
    removed: the results' own ``before_after``, else computed from the stored curves (no held-out)."""
    stored = results.get("before_after")
    if isinstance(stored, Mapping) and stored:
        return dict(stored)
    out: dict[str, Any] = {}
    for name, curve in (results.get("curves") or {}).items():
        centred = _datum_removed(curve)
        if centred is None:
            continue
        groups, before, after = centred
        out[name] = {"datum_removed": True, "held_out_scheme": None,
                     "groups": {str(int(g)): {"n": int(np.sum(groups == g)), "before": _stat(before[groups == g]),
                                              "after_in_sample": _stat(after[groups == g]), "after_held_out": None}
                                for g in np.unique(groups)},
                     "all": {"before": _stat(before), "after_in_sample": _stat(after), "after_held_out": None}}
    return out


def _stat_cells(stat: Any, unit: Unit) -> str:
    if not isinstance(stat, Mapping):
        return "<td>—</td><td>—</td>"
    return f"<td>{fmt(stat.get('rms'), unit.scale)}</td><td>{fmt(stat.get('max_abs'), unit.scale)}</td>"


def _before_after_html(results: Mapping[str, Any]) -> str:
    table = before_after(results)
    rows = []
    for name in (c for c in COMPONENTS if c in table):
        entry, unit = table[name], component_unit(name)
        groups = entry.get("groups") if isinstance(entry.get("groups"), Mapping) else {}
        for g, stats in list(groups.items()) + [("all", entry.get("all"))]:
            if not isinstance(stats, Mapping):
                continue
            n = stats.get("n") or (stats.get("before") or {}).get("n", "")
            css = " class=total" if g == "all" else ""
            rows.append(f"<tr{css}><td class=l>{name}</td><td>{escape(str(g))}</td><td>{n}</td>"
                        f"{_stat_cells(stats.get('before'), unit)}{_stat_cells(stats.get('after_in_sample'), unit)}"
                        f"{_stat_cells(stats.get('after_held_out'), unit)}<td class=l>{unit.symbol}</td></tr>")
    if not rows:
        return ""
    return ("<table class=cal><caption>Error = measured − reference, each group's datum (its mean error) removed. "
            "<b>In-sample</b>: the record's correction on the data it was fitted on (it shows the fit). "
            "<b>Held-out</b>: each point predicted by a fit without it (leave-one-point-out; the end points are "
            "never held out): what to expect between calibration points.</caption>"
            "<thead><tr><th class=l rowspan=2>component</th><th rowspan=2>group</th><th rowspan=2>n</th>"
            "<th colspan=2>before</th><th colspan=2>after, in-sample</th><th colspan=2>after, held-out</th>"
            "<th class=l rowspan=2>unit</th></tr><tr><th>RMS</th><th>max</th><th>RMS</th><th>max</th><th>RMS</th>"
            "<th>max</th></tr></thead><tbody>" + "".join(rows) + "</tbody></table>")


def _evaluation(results: Mapping[str, Any]) -> Mapping[str, Any]:
    """The held-out evaluation: the results' own (docs/results.md), else the fit summary's (older runs)."""
    for evaluation in (results.get("evaluation"), (results.get("summary") or {}).get("evaluation")):
        if isinstance(evaluation, Mapping) and isinstance(evaluation.get("rows"), list):
            return evaluation
    return {}


def _evaluation_rows(results: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    return [r for r in _evaluation(results).get("rows") or [] if isinstance(r, Mapping)]


def method_in_force(results: Mapping[str, Any], component: str) -> str | None:
    """The method the record applies to ``component``: as stored, else the lowest leave-one-point-out
    RMS (the one ``instrument.compensation.calibrate`` keeps)."""
    methods = _evaluation(results).get("method_in_force")
    if isinstance(methods, Mapping) and component in methods:
        return str(methods[component])
    rows = [r for r in _evaluation_rows(results) if r.get("component") == component]
    flagged = [r for r in rows if r.get("in_force")]
    if flagged:
        return str(flagged[0].get("method"))
    lopo = [r for r in rows if r.get("scheme") == LOPO and is_number(r.get("rms"))]
    return str(min(lopo, key=lambda r: r["rms"])["method"]) if lopo else None


def _row(results: Mapping[str, Any], component: str, method: str | None, scheme: str) -> Mapping[str, Any]:
    return next((r for r in _evaluation_rows(results) if r.get("component") == component
                 and r.get("method") == method and r.get("scheme") == scheme), {})


def _residual_figure(results: Mapping[str, Any], component: str) -> Figure | None:
    stored = (results.get("residual_uncertainty") or {}).get(component)
    return Figure.from_object(stored) if isinstance(stored, Mapping) and "value" in stored else None


def _heldout_html(results: Mapping[str, Any]) -> str:
    rows = _evaluation_rows(results)
    if not rows:
        return ""
    components = [c for c in COMPONENTS if any(r.get("component") == c for r in rows)]
    kept = []
    for c in components:
        unit, method = component_unit(c), method_in_force(results, c)
        lopo, logo = _row(results, c, method, LOPO), _row(results, c, method, LOGO)
        residual = _residual_figure(results, c)
        rms_cell = (figure_cell(residual, Unit(unit.symbol, unit.scale, 2, False)) if residual is not None
                    else f"<td>{fmt(lopo.get('rms'), unit.scale)}</td>")
        kept.append(f"<tr><td class=l>{c}</td><td class=l>{escape(str(method))}</td>{rms_cell}"
                    f"<td>{fmt(lopo.get('max_abs'), unit.scale)}</td><td>{lopo.get('n_heldout', '—')}</td>"
                    f"<td>{fmt(logo.get('rms'), unit.scale)}</td><td>{fmt(logo.get('max_abs'), unit.scale)}</td>"
                    f"<td>{fmt(lopo.get('noise_floor', logo.get('noise_floor')), unit.scale)}</td>"
                    f"<td class=l>{unit.symbol}</td></tr>")
    methods = sorted({str(r.get("method")) for r in rows})
    compare = []
    for c in components:
        unit = component_unit(c)
        cells = "".join(f"<td>{fmt(_row(results, c, m, LOPO).get('rms'), unit.scale)} / "
                        f"{fmt(_row(results, c, m, LOGO).get('rms'), unit.scale)}</td>" for m in methods)
        compare.append(f"<tr><td class=l>{c} ({unit.symbol})</td>{cells}</tr>")
    evaluation = _evaluation(results)
    note = evaluation.get("scheme_note") or evaluation.get("note") or ""
    u_note = (" RMS one point out: value ± U (k = 2, from the reference's noise and scale), in brackets its "
              "sampling interval over the calibration points." if any(_residual_figure(results, c) for c in components)
              else "")
    return (
        "<h3>Held-out evaluation</h3><table class=cal><caption>The method in force, scored on data it was not "
        "fitted on: one point out (each interior calibration point left out in turn, all its repeats and groups) "
        "and one group out (a whole group left out, its mean removed: the curve's shape). Residual = corrected − "
        f"reference.{u_note}</caption>"
        "<tr><th class=l>component</th><th class=l>method</th><th>RMS, one point out</th>"
        "<th>max, one point out</th><th>n held out</th><th>RMS, one group out</th><th>max, one group out</th>"
        "<th>noise floor</th><th class=l>unit</th></tr>" + "".join(kept) + "</table>"
        "<table class=cal><caption>All methods evaluated: held-out RMS, one point out / one group out</caption>"
        "<tr><th class=l>component</th>" + "".join(f"<th>{escape(m)}</th>" for m in methods) + "</tr>"
        + "".join(compare) + "</table>" + (f"<p class=note>{escape(str(note))}</p>" if note else "")
    )


def reference_vs_truth(results: Mapping[str, Any]) -> dict[str, Any]:
    """Reference − true per component: each group's datum offset apart from the scatter about it. The
    results' own ``reference_vs_truth`` when stored, else computed from the stored rows."""
    stored = results.get("reference_vs_truth")
    if isinstance(stored, Mapping) and stored:
        return dict(stored)
    out: dict[str, Any] = {}
    for name, entries in (results.get("data") or {}).items():
        pairs = [(e.get("group", 0), e["reference"] - e["true"]) for e in entries or []
                 if isinstance(e, Mapping) and is_number(e.get("true")) and is_number(e.get("reference"))]
        if not pairs:
            continue
        groups, diffs = np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
        per_group, residual = {}, np.zeros(diffs.size)
        for g in np.unique(groups):
            offset = float(np.mean(diffs[groups == g]))
            residual[groups == g] = diffs[groups == g] - offset
            per_group[str(int(g))] = {"datum_offset": offset, **_stat(diffs[groups == g] - offset)}
        out[name] = {"groups": per_group, "all": _stat(residual)}
    return out


def _truth_html(results: Mapping[str, Any]) -> str:
    table = reference_vs_truth(results)
    rows = []
    for name in (c for c in COMPONENTS if c in table):
        unit, entry = component_unit(name), table[name]
        groups = entry.get("groups") if isinstance(entry.get("groups"), Mapping) else {}
        for g, stats in list(groups.items()) + [("all", entry.get("all"))]:
            if not isinstance(stats, Mapping):
                continue
            css = " class=total" if g == "all" else ""
            offset = stats.get("datum_offset")
            rows.append(f"<tr{css}><td class=l>{name}</td><td>{escape(str(g))}</td><td>{stats.get('n', '')}</td>"
                        f"<td>{fmt(offset + 0.0 if is_number(offset) else None, unit.scale, 1)}</td>"
                        f"<td class=true>{fmt(stats.get('rms'), unit.scale, 3)}</td>"
                        f"<td class=true>{fmt(stats.get('max_abs'), unit.scale, 3)}</td>"
                        f"<td class=l>{unit.symbol}</td></tr>")
    if not rows:
        return ""
    return ("<h3>Reference against simulated truth</h3><table class=cal><caption>Reference − true, per group: the "
            "group's datum (where its reference reads zero in the cell's absolute frame: an offset, not an error) "
            "and the scatter about it (the reference's own error, comparable with the residuals above)</caption>"
            "<thead><tr><th class=l>component</th><th>group</th><th>n</th><th>datum offset</th>"
            "<th>RMS about the datum</th><th>max about the datum</th><th class=l>unit</th></tr></thead><tbody>"
            + "".join(rows) + "</tbody></table>")


def _fit_summary_html(results: Mapping[str, Any]) -> str:
    curves = results.get("curves") or {}
    summary = results.get("summary") or {}
    validity = results.get("validity") or summary.get("validity")
    rows = []
    for c in [c for c in COMPONENTS if c in curves or method_in_force(results, c)]:
        unit = component_unit(c)
        value_unit, value_scale = ("°", DEGREE) if unit.angular else ("mm", 1e3)
        measured = _array((curves.get(c) or {}).get("measured"))
        span = validity.get(c) if isinstance(validity, Mapping) else None
        if not (isinstance(span, (list, tuple)) and len(span) == 2) and measured.size:
            span = [float(measured.min()), float(measured.max())]
        span_text = (f"{fmt(span[0], value_scale, 3)} … {fmt(span[1], value_scale, 3)} {value_unit}"
                     if isinstance(span, (list, tuple)) and len(span) == 2 else "—")
        directions = sorted({int(d) for d in _array((curves.get(c) or {}).get("direction")) if np.isfinite(d)})
        rows.append(f"<tr><td class=l>{c}</td><td class=l>{escape(str(method_in_force(results, c) or '—'))}</td>"
                    f"<td>{measured.size or '—'}</td><td class=l>{span_text}</td>"
                    f"<td class=l>{', '.join(f'{d:+d}' for d in directions) or 'not recorded'}</td></tr>")
    if not rows:
        return ""
    method = summary.get("method") or summary.get("model")
    approach = results.get("approach")
    return ("<h3>Fit summary</h3>"
            + (f"<p>Method: {escape(str(method))}" + (f"; approached from {escape(str(approach))} direction(s)"
                                                       if approach else "") + ".</p>" if method else "")
            + "<table class=cal><tr><th class=l>component</th><th class=l>method in force</th><th>observations</th>"
            "<th class=l>validity range (measured values fitted)</th><th class=l>approach directions</th></tr>"
            + "".join(rows) + "</table>")


def _plots(results: Mapping[str, Any]) -> str:
    plots = []
    for name, curve in (results.get("curves") or {}).items():
        unit = component_unit(name)
        value_unit, value_scale = ("°", DEGREE) if unit.angular else ("mm", 1e3)
        measured, centred = _array(curve.get("measured")), _datum_removed(curve)
        if centred is None or centred[1].size != measured.size:
            continue
        groups, before, in_sample = centred
        held_out = _array([np.nan if v is None else v for v in curve.get("error_after_held_out") or []])
        panels = [("before", before), ("after, held-out", held_out) if held_out.size == measured.size
                  else ("after, in-sample", in_sample)]
        pair = []
        for title, errors in panels:
            series = [(f"group {int(g)}", measured[groups == g] * value_scale, errors[groups == g] * unit.scale)
                      for g in np.unique(groups)]
            pair.append(scatter(series, title=f"{name}: error {title}", xlabel=f"measured {name} ({value_unit})",
                                ylabel=f"error ({unit.symbol})", zero_line=True))
        plots.append(f"<div class='plots series' data-component='{escape(name)}'>{''.join(pair)}</div>")
    return "".join(plots)


def calibration_results_html(results: Mapping[str, Any]) -> str:
    """Errors per group with datums removed, held-out evaluation, reference against truth, fit summary, curves."""
    plots = _plots(results)
    return (
        "<section id=results><h2>Calibration</h2>"
        f"<p>Record written: <code class=hash>{escape(str(results.get('record_path')))}</code>, "
        f"id <code class=hash>{escape(str(results.get('record_id')))}</code>.</p>"
        + _before_after_html(results) + _heldout_html(results) + _truth_html(results) + _fit_summary_html(results)
        + "</section>"
        + (f"<section class=part id=plots><h2>Calibration curves</h2><p class=note>Error against the measured value, "
           f"per group, each group's datum removed.</p>{plots}</section>" if plots else "")
    )


def calibration_summary_lines(results: Mapping[str, Any]) -> list[str]:
    """``instrument show``: where the record went, and the held-out RMS per component."""
    lines = [f"record     {results['record_path']} ({results['record_id']})"]
    for c in COMPONENTS:
        method = method_in_force(results, c)
        row = _row(results, c, method, LOPO)
        if row:
            unit = component_unit(c)
            lines.append(f"held out   {c}: {fmt(row.get('rms'), unit.scale)} {unit.symbol} RMS, one point out "
                         f"({method})")
    return lines
