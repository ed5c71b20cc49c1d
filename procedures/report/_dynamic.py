"""Report sections of the runs measured in motion (pose stabilisation, path characteristics).

Stored in SI; shown in µm, ms, % and mm/s, said in every header. Each figure carries ``± U`` (k = 2)
where the run evaluated one, and in simulation the truth's figure beside it ("true").
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from html import escape
from typing import Any

import numpy as np

from procedures.report._format import fmt, is_number
from procedures.report._svg import lines

UM, MS = 1e6, 1e3


def _with_u(value: Any, u: Any, scale: float, digits: int = 2) -> str:
    text = fmt(value, scale, digits)
    return text + (f" ± {fmt(u, scale, digits)}" if is_number(u) else "")


def _true(entry: Mapping[str, Any] | None, key: str, scale: float, digits: int = 2) -> str:
    return fmt((entry or {}).get(key), scale, digits) if entry else "—"


def _table(head: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    header = "".join(f"<th>{escape(h)}</th>" for h in head)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table class=figures><thead><tr>{header}</tr></thead><tbody>{body}</tbody></table>"


def _notes(results: Mapping[str, Any]) -> str:
    u = results.get("uncertainty") or {}
    parts = []
    if u.get("covers"):
        parts.append("U (k = 2) covers: " + "; ".join(escape(str(c)) for c in u["covers"]) + ".")
    if u.get("not_covered"):
        parts.append("Not covered: " + "; ".join(escape(str(c)) for c in u["not_covered"]) + ".")
    if results.get("failed"):
        parts.append(f"Failed moves: {escape(', '.join(results['failed']))}.")
    return "".join(f"<p class=note>{p}</p>" for p in parts)


# ------------------------------------------------------------------------------ stabilisation
def stabilisation_html(results: Mapping[str, Any]) -> str:
    band = results.get("band")
    rows = []
    for s in results.get("settings") or []:
        st, os_ = s["stabilisation_time"], s["overshoot"]
        rows.append([escape(str(s["point"])), f"{s['speed_percent']:g}", fmt(s.get("speed"), 1e3, 0), str(s["cycles"]),
                     _with_u(st.get("mean"), st.get("expanded_uncertainty"), MS), fmt(st.get("max"), MS),
                     fmt(st.get("true_mean"), MS), str(st.get("never_settled", 0)),
                     _with_u(os_.get("mean"), os_.get("expanded_uncertainty"), UM), fmt(os_.get("max"), UM),
                     fmt(os_.get("true_mean"), UM)])
    table = _table(["point", "speed %", "speed mm/s", "cycles", "t_s mean ms ± U", "t_s max ms", "t_s true ms",
                    "never settled", "overshoot mean µm ± U", "overshoot max µm", "overshoot true µm"], rows)
    moves = [m for m in results.get("moves") or [] if "error" not in m]
    move_rows = [[escape(str(m.get("key"))), _with_u(m.get("stabilisation_time"), m.get("u_stabilisation_time"), MS),
                  _true(m.get("true"), "stabilisation_time", MS),
                  _with_u(m.get("overshoot"), m.get("u_overshoot"), UM), _true(m.get("true"), "overshoot", UM),
                  str(m.get("poses")), str(m.get("dropped"))] for m in moves]
    per_move = _table(["move", "t_s ms ± U", "t_s true ms", "overshoot µm ± U", "overshoot true µm", "poses",
                       "dropped"], move_rows)
    plots = "".join(_distance_plot(m, band) for m in moves if m.get("series"))
    positioning = results.get("positioning_time") or {}
    positioning_line = ""
    if positioning.get("minimum") is not None:
        per = ", ".join(f"{escape(k)}: {fmt(v, MS)} ms" for k, v in (positioning.get("per_setting") or {}).items())
        positioning_line = (f"<p>Minimum positioning time (ISO 9283 9): {fmt(positioning['minimum'], MS)} ms at "
                            f"{escape(str(positioning.get('setting')))} ({per}).</p>")
    return (f"<section class=part id=results><h2>Results: pose stabilisation (ISO 9283 7.4, 7.5)</h2>"
            f"<p>Band {fmt(band, UM)} µm ({escape(str(results.get('band_source')))}); times from the robot's done "
            f"signal; the tool point.</p>{table}{positioning_line}<h3>Distance to the attained pose</h3>"
            f"<div class=plots>{plots}</div><h3>Every move</h3>{per_move}{_notes(results)}</section>")


def _distance_plot(move: Mapping[str, Any], band: Any) -> str:
    series = move["series"]
    t = np.asarray(series["t"]) * MS
    d = np.asarray(series["value"]) * UM
    plotted: list[tuple[str, Any, Any]] = [("measured", t, d)]
    true = (move.get("true") or {}).get("series")
    if true:
        plotted.append(("true", np.asarray(true["t"]) * MS, np.asarray(true["value"]) * UM))
    if is_number(band):
        plotted.append(("band", [t[0], t[-1]], [band * UM, band * UM]))
    if is_number(move.get("stabilisation_time")):
        ts = move["stabilisation_time"] * MS
        plotted.append(("t_s", [ts, ts], [0.0, float(np.nanmax(d))]))
    return lines(plotted, title=f"{move.get('key')}", xlabel="ms after done", ylabel="µm", width=340, height=200)


def stabilisation_lines(results: Mapping[str, Any]) -> list[str]:
    out = [f"band {fmt(results.get('band'), UM)} µm ({results.get('band_source')})"]
    for s in results.get("settings") or []:
        st, os_ = s["stabilisation_time"], s["overshoot"]
        t_s = _with_u(st.get("mean"), st.get("expanded_uncertainty"), MS)
        out.append(f"{s['point']} {s['speed_percent']:g} %: t_s {t_s}"
                   f" ms (max {fmt(st.get('max'), MS)}), overshoot "
                   f"{_with_u(os_.get('mean'), os_.get('expanded_uncertainty'), UM)} µm, n {s['cycles']}")
    return out


# --------------------------------------------------------------------------------------- paths
PATH_PARTS = (("leg_1", "line P2→P3"), ("leg_2", "line P3→P4"), ("circle", "circle about P1"))


def path_html(results: Mapping[str, Any]) -> str:
    rows, corner_rows, velocity_rows, plots = [], [], [], []
    for s in results.get("settings") or []:
        speed = f"{s['speed_percent']:g}"
        for key, name in PATH_PARTS:
            f = s.get(key) or {}
            if "error" in f or not f:
                rows.append([speed, escape(name), escape(str(f.get("error", "not measured")))] + ["—"] * 5)
                continue
            rows.append([speed, escape(name), _with_u(f.get("at_p"), f.get("u_at_p"), UM),
                         _true(f.get("true"), "at_p", UM),
                         fmt(f.get("rt_p"), UM), _true(f.get("true"), "rt_p", UM),
                         " / ".join(fmt(f.get(k), 206264.8, 1) for k in ("at_a", "at_b", "at_c")),
                         " / ".join(fmt(f.get(k), 206264.8, 1) for k in ("rt_a", "rt_b", "rt_c"))])
            if f.get("deviation"):
                plotted: list[tuple[str, Any, Any]] = [("measured", np.arange(len(f["deviation"])),
                                                       np.asarray(f["deviation"]) * UM)]
                if (f.get("true") or {}).get("deviation"):
                    plotted.append(("true", np.arange(len(f["true"]["deviation"])),
                                    np.asarray(f["true"]["deviation"]) * UM))
                plots.append(lines(plotted, title=f"{name}, {speed} %", xlabel="calculation point",
                                   ylabel="|G − C| µm", width=300, height=180))
        c = s.get("corner") or {}
        if c and "error" not in c:
            corner_rows.append([speed, _with_u(c.get("cr"), c.get("u_cr"), UM), _true(c.get("true"), "cr", UM),
                                _with_u(c.get("co"), c.get("u_co"), UM), _true(c.get("true"), "co", UM)])
        v = s.get("velocity") or {}
        if v and "error" not in v:
            velocity_rows.append([speed, fmt(v.get("commanded"), 1e3, 1), fmt(v.get("mean_speed"), 1e3, 1),
                                  _with_u(v.get("av"), v.get("u_av"), 100.0), _true(v.get("true"), "av", 100.0),
                                  fmt(v.get("rv"), 100.0), _with_u(v.get("fv"), v.get("u_fv"), 1e3),
                                  _true(v.get("true"), "fv", 1e3)])
    transform = results.get("transform") or {}
    fitted = f"fitted on {transform.get('points')} settled poses" if transform.get("fitted") else "not fitted"
    return ("<section class=part id=results><h2>Results: path characteristics (ISO 9283 8.2, 8.3, 8.5, 8.6)</h2>"
            f"<p>The tool point, in the instrument's frame (robot↔M transform "
            f"{fitted}).</p>"
            + _table(["speed %", "path", "AT_p µm ± U", "AT_p true µm", "RT_p µm", "RT_p true µm", "AT_a/b/c ″",
                      "RT_a/b/c ″"], rows)
            + "<h3>Cornering at P3 (8.5)</h3>"
            + _table(["speed %", "CR µm ± U", "CR true µm", "CO µm ± U", "CO true µm"], corner_rows)
            + "<h3>Path velocity on P3→P4 (8.6)</h3>"
            + _table(["speed %", "commanded mm/s", "mean mm/s", "AV % ± U", "AV true %", "RV %", "FV mm/s ± U",
                      "FV true mm/s"], velocity_rows)
            + f"<h3>Deviation along the path</h3><div class=plots>{''.join(plots)}</div>{_notes(results)}</section>")


def path_lines(results: Mapping[str, Any]) -> list[str]:
    out = []
    for s in results.get("settings") or []:
        parts = []
        for key, _ in PATH_PARTS:
            f = s.get(key) or {}
            if f and "error" not in f:
                at_p = _with_u(f.get("at_p"), f.get("u_at_p"), UM)
                parts.append(f"{key} AT_p {at_p} µm RT_p {fmt(f.get('rt_p'), UM)} µm")
        c, v = s.get("corner") or {}, s.get("velocity") or {}
        if c and "error" not in c:
            parts.append(f"CR {fmt(c.get('cr'), UM)} µm CO {fmt(c.get('co'), UM)} µm")
        if v and "error" not in v:
            parts.append(f"AV {fmt(v.get('av'), 100.0)} % RV {fmt(v.get('rv'), 100.0)} % "
                         f"FV {fmt(v.get('fv'), 1e3)} mm/s")
        out.append(f"{s['speed_percent']:g} %: " + "; ".join(parts))
    return out
