"""The ISO 9283 results section: RP and AP tables with U (k = 2) and the sampling interval, a
worst-case row, drift, distance and multi-direction figures, the uncertainty budget,
equal-aspect position plots with the RP circle, and the per-cycle deviations of every point.

The results' shape is docs/results.md. Every part renders only what the stored results hold, so
runs stored by older code (no figure objects, no uncertainty, no truth) still render.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from html import escape
from typing import Any

import numpy as np

from procedures.report._format import (
    ARCSEC,
    Figure,
    figure_cell,
    figure_unit,
    fmt,
    interval,
    is_number,
)
from procedures.report._svg import Circle, lines, scatter

RP_FIGURES = ("rp_l", "rp_a", "rp_b", "rp_c")
AP_FIGURES = ("ap_p", "ap_x", "ap_y", "ap_z", "ap_a", "ap_b", "ap_c")
DRIFT_FIGURES = ("dap_p", "dap_a", "dap_b", "dap_c", "drp_l", "drp_a", "drp_b", "drp_c")
AD_FIGURES = ("ad_p", "ad_x", "ad_y", "ad_z", "ad_a", "ad_b", "ad_c")
RD_FIGURES = ("rd_p", "rd_x", "rd_y", "rd_z", "rd_a", "rd_b", "rd_c")
VAP_FIGURES = ("vap_p", "vap_a", "vap_b", "vap_c")
SIGNED = {"ap_x", "ap_y", "ap_z", "ap_a", "ap_b", "ap_c", "ad_x", "ad_y", "ad_z", "ad_a", "ad_b", "ad_c"}
VIEWS = ((0, 1, "x", "y"), (0, 2, "x", "z"), (1, 2, "y", "z"))


def figure_name(key: str) -> str:
    """``"rp_l"`` → ``RP<sub>l</sub>``, ``"dap_p"`` → ``dAP<sub>P</sub>``, ``"vap_a"`` → ``vAP<sub>a</sub>``."""
    stem, sub = key.rsplit("_", 1)
    head = stem[0] + stem[1:].upper() if stem[0] in "dv" and len(stem) > 2 else stem.upper()
    return f"{head}<sub>{'P' if sub == 'p' else sub}</sub>"


def uncertainty_object(results: Mapping[str, Any], owner: str, key: str, group: str = "points"
                       ) -> Mapping[str, Any] | None:
    """The figure object (``value``, ``expanded_uncertainty`` …, docs/results.md) of ``key`` at ``owner``
    (a point; a pair such as ``"P2-P4"`` under ``group="distances"``), if the run stores figures."""
    figures = ((results.get("figures") or {}).get(group) or {}).get(owner)
    obj = figures.get(key) if isinstance(figures, Mapping) else None
    return obj if isinstance(obj, Mapping) and "value" in obj else None


def figure(results: Mapping[str, Any], label: str, key: str, group: str = "points") -> Figure:
    """A figure: its figure object when the run stores one, else the ISO statistics of the point
    (runs stored before figure objects existed)."""
    entry = (results.get("points") or {}).get(label) or {} if group == "points" else {}
    stats = entry.get("stats") or {}
    obj = uncertainty_object(results, label, key, group)
    if obj is not None:
        return Figure.from_object(obj, fallback_interval=stats.get(f"{key}_ci"))
    value = stats.get(key)
    true = (entry.get("true_stats") or {}).get(key)
    return Figure(value=float(value) if is_number(value) else None, interval=interval(stats.get(f"{key}_ci")),
                  true=float(true) if is_number(true) else None)


def true_figure(results: Mapping[str, Any], label: str, key: str) -> Figure:
    """The figure of the simulated cell's true poses (no uncertainty, no interval)."""
    return Figure(value=figure(results, label, key).true)


def measured_labels(results: Mapping[str, Any]) -> list[str]:
    """The points that have figures, in the run's order."""
    points = results.get("points") or {}
    return [p for p in results.get("order") or [] if "stats" in (points.get(p) or {})]


def worst_case(results: Mapping[str, Any], key: str) -> tuple[str, Figure] | None:
    """The point whose figure is worst: the largest value, or the largest magnitude of a signed one."""
    found = [(label, figure(results, label, key)) for label in measured_labels(results)]
    found = [(label, f) for label, f in found if f.value is not None]
    if not found:
        return None
    return max(found, key=lambda item: abs(item[1].value or 0.0) if key in SIGNED else (item[1].value or 0.0))


def _head(keys: Sequence[str]) -> str:
    return "".join(f"<th>{figure_name(key)} ({figure_unit(key).symbol})</th>" for key in keys)


def _point_table(results: Mapping[str, Any], keys: Sequence[str], caption: str, *, with_truth: bool = True) -> str:
    """Per point a measured row and, in simulation and where ``with_truth``, a true row; the worst case last."""
    points = results.get("points") or {}
    rows = []
    for label in results.get("order") or []:
        entry = points.get(label) or {}
        if "stats" not in entry:
            rows.append(f"<tr><td class=l>{escape(label)}</td><td>{entry.get('n', 0)}</td>"
                        f"<td class='l bad' colspan={len(keys)}>{escape(str(entry.get('error', '')))}</td></tr>")
            continue
        cells = "".join(figure_cell(figure(results, label, key), figure_unit(key)) for key in keys)
        rows.append(f"<tr data-point='{escape(label)}'><td class=l>{escape(label)}</td><td>{entry.get('n', '')}</td>"
                    f"{cells}</tr>")
        truth = [true_figure(results, label, key) for key in keys] if with_truth else []
        if any(t.value is not None for t in truth):
            cells = "".join(figure_cell(t, figure_unit(key), css="true") for t, key in zip(truth, keys))
            rows.append(f"<tr class=true><td class='l true'>{escape(label)} (true)</td><td></td>{cells}</tr>")
    worst = []
    for key in keys:
        found = worst_case(results, key)
        if found is None:
            worst.append("<td>—</td>")
            continue
        label, fig = found
        cell = figure_cell(Figure(fig.value, fig.expanded_uncertainty, fig.coverage_factor, None, None,
                                  fig.meets_rule), figure_unit(key))
        worst.append(cell[: -len("</td>")] + f"<br><small>at {escape(label)}</small></td>")
    rows.append(f"<tr class=worst><td class=l>worst case</td><td></td>{''.join(worst)}</tr>")
    return (f"<table class=figures><caption>{caption}</caption>"
            f"<thead><tr><th class=l>point</th><th>n</th>{_head(keys)}</tr></thead><tbody>{''.join(rows)}</tbody>"
            "</table>")


def _owner_table(results: Mapping[str, Any], group: str, keys: Sequence[str], caption: str, owner_name: str) -> str:
    """Figures stored only as figure objects (drift, distances, directions), one row per owner."""
    owners = (results.get("figures") or {}).get(group) or {}
    rows = []
    for owner, figs in owners.items() if isinstance(owners, Mapping) else ():
        present = [k for k in keys if isinstance(figs, Mapping) and k in figs]
        if not present:
            continue
        cells = "".join(figure_cell(figure(results, owner, key, group), figure_unit(key), show_true=True)
                        for key in keys)
        rows.append(f"<tr><td class=l>{escape(str(owner))}</td>{cells}</tr>")
    if not rows:
        return ""
    return (f"<table class=figures><caption>{caption}</caption><thead><tr><th class=l>{owner_name}</th>"
            f"{_head(keys)}</tr></thead><tbody>" + "".join(rows) + "</tbody></table>")


def _uncertainty(results: Mapping[str, Any]) -> Mapping[str, Any]:
    value = results.get("uncertainty")
    return value if isinstance(value, Mapping) else {}


def _with_u(results: Mapping[str, Any]) -> bool:
    return any(figure(results, label, key).expanded_uncertainty is not None
               for label in measured_labels(results) for key in RP_FIGURES + AP_FIGURES)


def _budget_html(results: Mapping[str, Any]) -> str:
    """The uncertainty budget: each term's standard uncertainty per pose component (µm, ″), the noise
    estimator, points outside a calibration's validity, notes."""
    unc = _uncertainty(results)
    if unc.get("evaluated") is False:
        return (f"<p class='note bad'>Measurement uncertainty not evaluated: {escape(str(unc.get('reason') or ''))}"
                "</p>")
    terms = (unc.get("budget") or {}).get("terms") if isinstance(unc.get("budget"), Mapping) else None
    if not isinstance(terms, list) or not terms:
        return ""
    rows = []
    for term in (t for t in terms if isinstance(t, Mapping)):
        u = term.get("standard_uncertainty")
        cells = "".join(f"<td>{fmt(u.get(c) if isinstance(u, Mapping) else None, 1e6 if c in 'xyz' else 1 / ARCSEC, 3)}"
                        "</td>" for c in "xyzabc")
        dof = term.get("dof")
        rows.append(f"<tr><td class=l>{escape(str(term.get('name', '')))}<br><small>"
                    f"{escape(str(term.get('source') or ''))}</small></td>"
                    f"<td class=l>{escape(str(term.get('correlation', '')))}</td>"
                    f"<td class=l>{escape(str(term.get('distribution', '')))}</td>"
                    f"<td>{f'{dof:g}' if is_number(dof) else '∞'}</td>{cells}</tr>")
    extra = []
    estimator = unc.get("noise_estimator")
    if isinstance(estimator, Mapping) and estimator.get("used"):
        extra.append(f"Frame noise from: {escape(str(estimator['used']))}"
                     + (f" ({escape(str(estimator.get('why')))})" if estimator.get("why") else "") + ".")
    outside = unc.get("outside_validity")
    if isinstance(outside, Mapping) and outside:
        where = "; ".join(f"{escape(str(p))}: {escape(', '.join(map(str, c)))}" for p, c in outside.items())
        extra.append(f"<span class=bad>Outside a calibration's validity range (correction extrapolated, its "
                     f"uncertainty inflated)</span>: {where}.")
    for note in unc.get("notes") or []:
        extra.append(escape(str(note)))
    method = unc.get("method")
    draws = f", {unc['draws']} draws, seed {unc.get('seed')}" if is_number(unc.get("draws")) else ""
    return ("<h3>Uncertainty budget</h3><table class=budget><caption>Standard uncertainty (k = 1) of each source "
            "per pose component; propagated to every figure by "
            + escape(str(method or "Monte Carlo through the ISO 9283 formulas")) + f"{draws}</caption>"
            "<thead><tr><th class=l>term and source</th><th class=l>correlation</th><th class=l>distribution</th>"
            "<th>dof</th><th>u<sub>x</sub> (µm)</th><th>u<sub>y</sub> (µm)</th><th>u<sub>z</sub> (µm)</th>"
            "<th>u<sub>a</sub> (″)</th><th>u<sub>b</sub> (″)</th><th>u<sub>c</sub> (″)</th></tr></thead><tbody>"
            + "".join(rows) + "</tbody></table>" + "".join(f"<p class=note>{e}</p>" for e in extra))


def _position_plots(results: Mapping[str, Any], label: str) -> str:
    entry = (results.get("points") or {}).get(label) or {}
    poses = np.asarray(entry.get("poses") or [], float)
    if poses.ndim != 2 or poses.shape[0] < 2 or poses.shape[1] < 3:
        return ""
    centred = (poses[:, :3] - poses[:, :3].mean(axis=0)) * 1e6
    true = np.asarray(entry.get("true_poses") or [], float)
    true_centred = (true[:, :3] - true[:, :3].mean(axis=0)) * 1e6 if true.ndim == 2 and len(true) >= 2 else None
    rp_l = figure(results, label, "rp_l").value
    circles = [Circle(0.0, 0.0, rp_l * 1e6, f"RP_l = {rp_l * 1e6:.2f} µm")] if rp_l is not None else []
    plots = []
    for i, j, a, b in VIEWS:
        series: list[tuple[str, Any, Any]] = [("measured", centred[:, i], centred[:, j])]
        if true_centred is not None:
            series.append(("true (simulation)", true_centred[:, i], true_centred[:, j]))
        plots.append(scatter(series, title=f"{label}: {a}–{b} about the barycentre", xlabel=f"Δ{a} (µm)",
                             ylabel=f"Δ{b} (µm)", equal_aspect=True, circles=circles))
    return f"<div class=plots data-point='{escape(label)}'>{''.join(plots)}</div>"


def _cycle_numbers(entry: Mapping[str, Any], n: int) -> np.ndarray:
    """Cycle number of each pose, counted from 1 (stored from 0), else the pose's rank."""
    cycles = entry.get("cycles")
    if isinstance(cycles, list) and len(cycles) == n and all(is_number(c) for c in cycles):
        values = np.asarray(cycles, float)
        return values + 1 if values.min() == 0 else values
    return np.arange(1, n + 1, dtype=float)


def _cycle_plots(results: Mapping[str, Any], label: str) -> str:
    entry = (results.get("points") or {}).get(label) or {}
    poses = np.asarray(entry.get("poses") or [], float)
    if poses.ndim != 2 or poses.shape[0] < 2 or poses.shape[1] < 6:
        return ""
    x = _cycle_numbers(entry, len(poses))
    deviation = poses - poses.mean(axis=0)
    position = [(f"Δ{c}", x, deviation[:, k] * 1e6) for k, c in enumerate("xyz")]
    angle = [(f"Δ{c}", x, deviation[:, 3 + k] / ARCSEC) for k, c in enumerate("abc")]
    return (f"<div class='plots series' data-point='{escape(label)}'>"
            + lines(position, title=f"{label}: position − mean pose", xlabel="cycle", ylabel="deviation (µm)")
            + lines(angle, title=f"{label}: orientation − mean pose", xlabel="cycle", ylabel="deviation (″)")
            + "</div>")


def _context_html(results: Mapping[str, Any]) -> str:
    transform = results.get("transform") or {}
    if transform.get("fitted"):
        text = (f"End-effector transform step: robot↔M rigid fit over {transform.get('points')} poses, "
                f"residual RMS {fmt(transform.get('residual_rms'), 1e6)} µm.")
    else:
        text = "No end-effector transform step (AP against the nominal frame M)."
    comp = results.get("compensation") or []
    comp_text = (f"Compensation applied with record(s) <code class=hash>{escape(', '.join(map(str, comp)))}</code>."
                 if comp else "<b>No compensation applied.</b>")
    return f"<p>{text} {comp_text}</p>"


def _legend_html(results: Mapping[str, Any]) -> str:
    n = max((int((results.get("points") or {})[p].get("n", 0)) for p in measured_labels(results)), default=0)
    cells = ("Each cell: value ± U, the instrument's expanded uncertainty (k = 2), where evaluated; angles in "
             "arc-seconds with degrees below; in brackets the 95 % sampling confidence interval of the figure over "
             f"the n = {n} cycles (where ISO 9283's formulas give one): U says how well these cycles were measured, "
             "the interval how much another set of cycles could differ. "
             "† U above 25 % of the figure (the usual rule for a measuring instrument is not met).")
    if not _with_u(results):
        cells += " <b>No uncertainty in this run</b>" + (
            " (stored before it was computed)." if "figures" not in results else ".")
    values = (" Values are the ISO formula's corrected for the instrument's noise bias (see the budget); the "
              "formula's own values are in the appendix." if _with_u(results) else "")
    points = results.get("points") or {}
    truth = ("Rows marked (true), in the repeatability table only, are the same RP figures of the poses the "
             "simulated cell really attained: RP is a spread about each point's own mean, so it compares like for "
             "like and measured − true is the instrument's error. Pose accuracy has no true row: the measured AP is "
             "against the commanded poses after the transform step, while the cell's true tool point carries the "
             "OPR and tool mounting errors the cell hides from the instrument, so a true AP would not compare with "
             "it (the two differ by those mounting errors, not by the instrument's error).")
    has_truth = any("true_stats" in (points.get(p) or {}) for p in results.get("order") or []) or any(
        figure(results, p, "rp_l").true is not None for p in measured_labels(results))
    return f"<p class=note>{cells}{values}</p>" + (f"<p class=note>{truth}</p>" if has_truth else "")


def iso_results_html(results: Mapping[str, Any]) -> str:
    """The ISO 9283 section: tables, budget, position plots and per-cycle deviations (SI → µm, ″)."""
    order = results.get("order") or []
    plots = "".join(_position_plots(results, p) for p in order)
    series = "".join(_cycle_plots(results, p) for p in order)
    extra = (_owner_table(results, "points", DRIFT_FIGURES, "Pose drift: first cycles against the last", "point")
             + _owner_table(results, "distances", AD_FIGURES, "Distance accuracy AD", "pair")
             + _owner_table(results, "distances", RD_FIGURES, "Distance repeatability RD", "pair")
             + _owner_table(results, "directions", VAP_FIGURES, "Multi-directional pose accuracy variation vAP",
                            "point"))
    return (
        "<section id=results><h2>ISO 9283 pose repeatability and accuracy</h2>"
        + _context_html(results)
        + _point_table(results, RP_FIGURES, "Pose repeatability RP (RP<sub>l</sub> = l̄ + 3·S<sub>l</sub>; "
                       "RP<sub>a,b,c</sub> = ±3·S)")
        + _point_table(results, AP_FIGURES, "Pose accuracy AP against the commanded pose (after the transform step)",
                       with_truth=False)
        + _legend_html(results) + extra + _budget_html(results) + "</section>"
        + ("<section class=part id=plots><h2>Attained positions</h2><p class=note>Positions about each point's "
           "barycentre, equal scales on both axes; the dashed circle has the radius RP<sub>l</sub>.</p>"
           f"{plots}</section>" if plots else "")
        + ("<section class=part id=cycles><h2>Deviations per cycle</h2><p class=note>Each pose's deviation from "
           "its point's mean pose, in cycle order: a trend is drift, a settling start is warm-up.</p>"
           f"{series}</section>" if series else "")
    )


def iso_summary_lines(results: Mapping[str, Any]) -> list[str]:
    """``instrument show``: RP and AP per point, in µm and arc-seconds, with U where the run has it."""
    out = ["point  n    RP_l (µm)  RP_a (″)   RP_b (″)   RP_c (″)   AP_P (µm)   U(RP_l) U(AP_P) (µm, k=2)"]
    for label in results.get("order") or []:
        entry = (results.get("points") or {}).get(label) or {}
        if "stats" not in entry:
            out.append(f"{label:<5} {entry.get('n', 0):>3}  {entry.get('error', '')}")
            continue
        figs = {key: figure(results, label, key) for key in ("rp_l", "rp_a", "rp_b", "rp_c", "ap_p")}
        shown = {key: f"{f.value * (1e6 if key in ('rp_l', 'ap_p') else 1 / ARCSEC):9.2f}" if f.value is not None
                 else f"{'—':>9}" for key, f in figs.items()}
        u = "  ".join(fmt(figs[key].expanded_uncertainty, 1e6).rjust(7) for key in ("rp_l", "ap_p"))
        out.append(f"{label:<5} {entry.get('n', 0):>3}  {shown['rp_l']}  {shown['rp_a']}  {shown['rp_b']}  "
                   f"{shown['rp_c']}  {shown['ap_p']}   {u}")
    return out
