"""The report's title, its banner of deviations from ISO 9283, and the test conditions.

The run's results say what deviated and under which conditions it was measured (``deviations``,
``test_conditions``, docs/results.md). A run stored before that still gets the deviations that can
be read off the run itself (fewer than 30 cycles; compensation asked for but no record in force, or
not asked for) and the conditions its parameters and station snapshot hold, each saying where it
came from.
"""

from __future__ import annotations

import re
import time
from collections.abc import Mapping
from html import escape
from typing import Any

from procedures.report._format import display_json, fmt, is_number, key_value_table
from procedures.report._sections import kind_of_run

ISO_CYCLES = 30
KELVIN = 273.15


def as_mapping(value: Any) -> Mapping[str, Any]:
    """``value`` if it is a mapping, else an empty one (stored JSON may hold anything)."""
    return value if isinstance(value, Mapping) else {}


def _judged_against_iso(run: Mapping[str, Any]) -> bool:
    """Whether the run's kind is judged against ISO 9283's test conditions (``iso_test_conditions``)."""
    kind = kind_of_run(run)
    return kind is not None and kind.iso_test_conditions


def _conditions(run: Mapping[str, Any]) -> Mapping[str, Any]:
    stored = (run.get("results") or {}).get("test_conditions")
    return stored if isinstance(stored, Mapping) else {}


def cycles_measured(run: Mapping[str, Any]) -> int | None:
    """The fewest cycles measured at a point (finished ISO runs), else the cycles planned."""
    results = run.get("results") or {}
    counts = [int(p.get("n", 0)) for p in (results.get("points") or {}).values() if isinstance(p, Mapping)]
    if counts:
        return min(counts)
    cycles = (run.get("parameters") or {}).get("cycles")
    return int(cycles) if is_number(cycles) else None


def report_title(run: Mapping[str, Any]) -> str:
    """A title that states what was measured, as the run's kind words it from the parameters the run had
    (never the procedure file's name, which may say "30 cycles" of a 5-cycle run); the file's name, or the
    procedure's, for a kind no longer known."""
    kind = kind_of_run(run)
    if kind is None:
        return str(run.get("procedure_name") or run["procedure"])
    return kind.title(run.get("parameters") or {}, run.get("results"))


def name_note(run: Mapping[str, Any]) -> str:
    """The procedure file's name, with a warning when it claims a cycle count the run did not measure."""
    name = str(run.get("procedure_name") or "")
    match = re.search(r"(\d+)\s*cycles?", name)
    n = cycles_measured(run)
    if match and n is not None and int(match.group(1)) != n:
        return f"{escape(name)} <span class=bad>(the name says {match.group(1)} cycles; this run has {n})</span>"
    return escape(name)


def derived_deviations(run: Mapping[str, Any]) -> list[str]:
    """Deviations from ISO 9283 read off a run of a kind judged against its test conditions (for runs whose
    results carry none)."""
    if not _judged_against_iso(run):
        return []
    params, results = run.get("parameters") or {}, run.get("results") or {}
    found = []
    n = cycles_measured(run)
    if n is not None and n < ISO_CYCLES:
        found.append(f"{n} cycles {'measured' if results else 'planned'} (ISO 9283 asks for {ISO_CYCLES}): the "
                     "repeatability rests on fewer poses")
    if results:
        in_force = results.get("compensation") or []
        if params.get("apply_compensation", True) and not in_force:
            found.append("compensation requested (apply_compensation: true) but no calibration record was in force: "
                         "the poses are uncorrected")
        elif not params.get("apply_compensation", True):
            found.append("no compensation: the poses are uncorrected (apply_compensation: false)")
        failed = [p for p, e in (results.get("points") or {}).items() if isinstance(e, Mapping) and "stats" not in e]
        if failed:
            found.append(f"no figures at {', '.join(failed)} (too few measured poses)")
    return found


def _deviation_item(item: Any) -> tuple[str, str]:
    """(severity, HTML) of one stored deviation."""
    if isinstance(item, Mapping):
        text = item.get("message") or item.get("code") or ""
        code = f" <small class=muted>[{escape(str(item['code']))}]</small>" if item.get("code") else ""
        return str(item.get("severity") or "deviation"), escape(str(text)) + code
    return "deviation", escape(str(item))


def banner_html(run: Mapping[str, Any]) -> str:
    """The deviations from ISO 9283 (and warnings on the measurement), at the top of the report."""
    results = run.get("results") or {}
    stored = results.get("deviations")
    is_iso = _judged_against_iso(run)
    if isinstance(stored, list):
        items = [_deviation_item(d) for d in stored]
        source = ""
    else:
        items = [("deviation", escape(d)) for d in derived_deviations(run)]
        source = (" <small>(read off the run: its results carry no list of deviations)</small>"
                  if is_iso and results else "")
    deviations = [html for severity, html in items if severity != "warning"]
    warnings = [html for severity, html in items if severity == "warning"]
    parts = []
    if deviations:
        heading = "Deviations from ISO 9283" if is_iso else "Deviations"
        parts.append(f"<div class=banner id=deviations><b>{heading}</b>{source}<ul>"
                     + "".join(f"<li>{d}</li>" for d in deviations) + "</ul></div>")
    elif is_iso and results:
        parts.append(f"<div class='banner ok' id=deviations><b>No deviation from ISO 9283 recorded.</b>{source}</div>")
    if warnings:
        parts.append("<div class='banner warn' id=warnings><b>Warnings on the measurement</b><ul>"
                     + "".join(f"<li>{w}</li>" for w in warnings) + "</ul></div>")
    return "".join(parts)


# --------------------------------------------------------------------------- values with units in their keys

def local_time(stamp: Any) -> str:
    """Seconds since the epoch as local date and time, or a dash."""
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(stamp)) if is_number(stamp) and stamp > 0 else "—"


def quantity(key: str, value: Any, *, difference: bool = False) -> str:
    """A stored SI value shown in the report's unit, chosen by its key (``speed_m_s`` → mm/s,
    ``air_temperature_k`` → °C, or K for a ``difference``, ``relative_humidity`` → %, ``pressure_pa``
    → hPa …); lists of numbers in parentheses; anything else as text."""
    k = key.lower()
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, (list, tuple)) and all(not isinstance(v, (Mapping, list, tuple)) for v in value):
        shown = [quantity(key, v, difference=difference) for v in value]
        unit = shown[0].split(" ", 1)[1] if shown and " " in shown[0] and is_number(value[0]) else ""
        numbers = [s.split(" ", 1)[0] if unit and s.endswith(unit) else s for s in shown]
        return "(" + ", ".join(numbers) + ")" + (f" {unit}" if unit else "")
    if isinstance(value, Mapping):
        return mapping_table(value, difference=difference, css="kv nested")
    if isinstance(value, (list, tuple)):
        return f"<pre class=inline>{escape(display_json(value))}</pre>"
    if not is_number(value):
        return escape(str(value))
    if k.endswith(("temperature_k", "temperatures_k")):
        return f"{value:.3f} K" if difference else f"{value - KELVIN:.2f} °C"
    if k == "relative_humidity":
        return f"{value * 100:.1f} %"
    if k.endswith("_pa"):
        return f"{value / 100:.2f} hPa"
    if k.endswith("_m") and 0 < abs(value) < 1e-3:  # noise, residuals: µm, where mm would read 0.000
        return f"{value * 1e6:.3f} µm"
    table = (("_m_s2", "mm/s²", 1e3, 1), ("_mm_s2", "mm/s²", 1, 1), ("_m_s", "mm/s", 1e3, 1),
             ("_mm_s", "mm/s", 1, 1), ("_m", "mm", 1e3, 3), ("_rad", "°", 57.29577951308232, 4),
             ("_kg", "kg", 1, 3), ("_s", "s", 1, 1), ("percent", "%", 1, 1), ("_ppm", "ppm", 1, 3))
    for suffix, unit, scale, digits in table:
        if k.endswith(suffix):
            return f"{value * scale:.{digits}f} {unit}"
    if k in ("time", "started", "finished", "start", "end") and value > 1e8:
        return local_time(value)
    return f"{value:.10g}" if isinstance(value, float) else str(value)


def label_of(key: str) -> str:
    """``"speed_percent_of_envelope"`` → "speed, % of envelope"; unit suffixes dropped (the value carries them)."""
    text = re.sub(r"_(m_s2|mm_s2|m_s|mm_s|m|rad|kg|s|pa|k|ppm)$", "", key)
    text = text.replace("_percent_of_", ", % of ").replace("percent_of_", "% of ")
    return text.replace("_", " ")


def mapping_table(values: Mapping[str, Any], *, difference: bool = False, skip: tuple[str, ...] = (),
                  css: str = "kv") -> str:
    """A key–value table of a mapping of SI values (a nested mapping as a table in its cell)."""
    rows = [(label_of(str(k)), quantity(str(k), v, difference=difference or k == "drift"))
            for k, v in values.items() if k not in skip]
    return key_value_table(rows, css=css)


# --------------------------------------------------------------------------- the sections of the conditions

def _robot(robot: Any) -> str:
    if not isinstance(robot, Mapping):
        return ""
    if robot.get("error"):
        return ("<h3>Robot</h3>" + key_value_table([("identity", f"<span class=bad>not read from the controller: "
                                                                 f"{escape(str(robot['error']))}</span>")]))
    rows = [(label_of(k), escape(str(robot.get(k) or "—")))
            for k in ("manufacturer", "model", "serial_number", "controller_version")]
    rows.append(("source", escape(str(robot.get("source") or "—"))
                 + (" (read from the controller, not typed in)" if robot.get("source") == "controller" else "")))
    return "<h3>Robot</h3>" + key_value_table(rows)


def _payload(payload: Any) -> str:
    if not isinstance(payload, Mapping):
        return ""
    rows = [("mass", quantity("mass_kg", payload.get("mass_kg"))),
            ("centre of gravity (flange frame)", quantity("cog_m", payload.get("cog_m"))),
            ("set on the robot", quantity("", payload.get("set_on_robot"))),
            ("rated payload", quantity("mass_kg", payload.get("rated_mass_kg"))),
            ("of rated", quantity("percent", payload.get("percent_of_rated")))]
    return "<h3>Payload</h3>" + key_value_table(rows)


def _motion(motion: Any) -> str:
    if not isinstance(motion, Mapping):
        return ""
    speed = quantity("speed_m_s", motion.get("speed_m_s"))
    acc = quantity("acceleration_m_s2", motion.get("acceleration_m_s2"))
    rows = [("TCP speed", f"{speed} ({quantity('percent', motion.get('speed_percent_of_envelope'))} of the station's "
                          f"limit; {quantity('percent', motion.get('percent_of_rated_speed'))} of rated "
                          f"{quantity('rated_speed_m_s', motion.get('rated_speed_m_s'))})"),
            ("TCP acceleration", f"{acc} ({quantity('percent', motion.get('acceleration_percent_of_envelope'))} of the "
                                 f"station's limit; {quantity('percent', motion.get('percent_of_rated_acceleration'))} "
                                 f"of rated {quantity('rated_m_s2', motion.get('rated_acceleration_m_s2'))})")]
    return "<h3>Motion</h3>" + key_value_table(rows)


def _mm(values: Any, count: int = 3) -> str:
    if not isinstance(values, (list, tuple)) or len(values) < count:
        return "—"
    return ", ".join(fmt(v, 1e3, 3) for v in values[:count])


def _cube(cube: Any, cycles: Any) -> str:
    if not isinstance(cube, Mapping):
        return ""
    rows = [("edge", quantity("edge_m", cube.get("edge_m"))),
            ("largest edge the envelope holds", quantity("edge_m", cube.get("largest_edge_m"))),
            ("centre in M", f"({_mm(cube.get('centre_in_m'))}) mm"),
            ("centre in the robot base frame", f"({_mm(cube.get('centre_in_base'))}) mm")]
    if isinstance(cycles, Mapping):
        rows.append(("cycles planned", escape(str(cycles.get("planned", "—")))))
    measured = cycles.get("measured") if isinstance(cycles, Mapping) else None
    points = as_mapping(cube.get("points"))
    point_rows = "".join(
        f"<tr><td class=l>{escape(str(p))}</td><td>{_mm((v or {}).get('in_m'))}</td>"
        f"<td>{_mm((v or {}).get('in_base'))}</td>"
        f"<td>{', '.join(fmt(a, 57.29577951308232, 3) for a in ((v or {}).get('in_base') or [])[3:6]) or '—'}</td>"
        f"<td>{escape(str(measured.get(p, '—'))) if isinstance(measured, Mapping) else '—'}</td></tr>"
        for p, v in points.items())
    table = ("<table><caption>Commanded poses P1–P5</caption><tr><th class=l>point</th><th>x, y, z in M (mm)</th>"
             "<th>TCP x, y, z in base (mm)</th><th>TCP rotation vector in base (°)</th><th>cycles measured</th></tr>"
             f"{point_rows}</table>") if point_rows else ""
    return "<h3>Cube and poses</h3>" + key_value_table(rows) + table


ENVIRONMENT_KEYS = ("air_temperature_k", "pressure_pa", "relative_humidity", "material_temperatures_k")


def _environment(environment: Any) -> str:
    if environment is None:
        return "<h3>Environment</h3><p class=bad>Not recorded (the station has no environmental unit).</p>"
    if not isinstance(environment, Mapping):
        return ""
    columns = [c for c in ("start", "mean", "end", "drift") if isinstance(environment.get(c), Mapping)]
    head = "".join(f"<th>{'drift (end − start)' if c == 'drift' else c}</th>" for c in columns)
    rows = "".join(
        f"<tr><th class=l>{label_of(k)}</th>"
        + "".join(f"<td>{quantity(k, environment[c].get(k), difference=c == 'drift')}</td>" for c in columns)
        + "</tr>" for k in ENVIRONMENT_KEYS if any(k in environment[c] for c in columns))
    source = (f"<p class=note>{escape(str(environment.get('source') or ''))}, "
              f"{escape(str(environment.get('readings', '—')))} readings.</p>")
    return f"<h3>Environment</h3>{source}<table><tr><th></th>{head}</tr>{rows}</table>" if columns else ""


def _warm_up(warm_up: Any) -> str:
    if not isinstance(warm_up, Mapping):
        return ""
    mode = warm_up.get("mode")
    text = {"run": "run by the instrument before the cycles", "declared": "declared by the operator"}.get(
        str(mode), escape(str(mode)))
    rows = [("warm-up", text), ("duration", quantity("duration_s", warm_up.get("duration_s")))]
    if warm_up.get("ran_s") is not None:
        rows.append(("ran", f"{quantity('ran_s', warm_up.get('ran_s'))}, {warm_up.get('moves', '—')} moves"))
    return "<h3>Warm-up</h3>" + key_value_table(rows)


def _records(records: Any) -> str:
    if not isinstance(records, list) or not records:
        return "<p class=bad>No calibration record in force.</p>"
    rows = []
    for record in (r for r in records if isinstance(r, Mapping)):
        validity = as_mapping(record.get("validity"))
        spans = "<br>".join(
            escape(f"{c}: {fmt(v[0], 1e3 if c in 'xyz' else 57.29577951308232, 2)} … "
                   f"{fmt(v[1], 1e3 if c in 'xyz' else 57.29577951308232, 2)} {'mm' if c in 'xyz' else '°'}")
            for c, v in validity.items() if isinstance(v, (list, tuple)) and len(v) == 2)
        methods = as_mapping(record.get("methods"))
        rows.append(f"<tr><td class=l><code class=hash>{escape(str(record.get('id')))}</code><br><small>"
                    f"{escape(str(record.get('path') or ''))}</small></td>"
                    f"<td class=l>{'<br>'.join(escape(f'{c}: {m}') for c, m in methods.items()) or '—'}</td>"
                    f"<td class=l>{escape(str(record.get('date') or '—'))}<br><small>run <code class=hash>"
                    f"{escape(str(record.get('run_id') or '—'))}</code></small></td>"
                    f"<td class=l nowrap>{spans or '—'}</td>"
                    f"<td class=l>{quantity('', record.get('bidirectional'))}</td>"
                    f"<td class=l>{quantity('', record.get('applied'))}</td></tr>")
    return ("<table><caption>Calibration records</caption><tr><th class=l>record</th><th class=l>method per "
            "component</th><th class=l>calibrated</th><th class=l>validity range</th><th class=l>both approach "
            "directions</th><th class=l>applied</th></tr>" + "".join(rows) + "</table>")


def _measurement_system(system: Any) -> str:
    if not isinstance(system, Mapping):
        return ""
    return ("<h3>Measurement system</h3>" + mapping_table(system, skip=("calibration_records",))
            + _records(system.get("calibration_records")))


def _sessions(sessions: Any) -> str:
    if not isinstance(sessions, list) or len(sessions) < 2:
        return ""
    rows = "".join(
        f"<tr><td class=l>{quantity('started', s.get('started'))}</td>"
        f"<td class=l>{escape(str((s.get('robot') or {}).get('serial_number') or '—'))}</td>"
        f"<td class=l>{quantity('mass_kg', (s.get('payload') or {}).get('mass_kg'))}</td>"
        f"<td class=l>{escape(str((s.get('operator') or {}).get('name') or '—'))}</td></tr>"
        for s in sessions if isinstance(s, Mapping))
    return ("<h3>Sessions</h3><table><caption>The run was measured in several sessions (resumed)</caption><tr>"
            "<th class=l>started</th><th class=l>robot serial</th><th class=l>payload</th><th class=l>operator</th>"
            f"</tr>{rows}</table>")


def _operator(operator: Any) -> str:
    if isinstance(operator, Mapping):
        name = operator.get("name")
        source = operator.get("source")
        return escape(str(name or "not recorded")) + (f" <small>(from {escape(str(source))})</small>" if source
                                                      else "")
    return escape(str(operator)) if operator else "not recorded"


KNOWN = ("standard", "date", "operator", "robot", "payload", "motion", "cube", "cycles", "environment", "warm_up",
         "measurement_system", "sessions")


def stored_conditions_html(conditions: Mapping[str, Any]) -> str:
    """The recorded test conditions (docs/results.md), in display units; keys not known here as a table."""
    head = [(key, escape(str(conditions[key]))) for key in ("standard", "date") if conditions.get(key)]
    head.append(("operator", _operator(conditions.get("operator"))))
    rest = {k: v for k, v in conditions.items() if k not in KNOWN}
    return (key_value_table(head) + _robot(conditions.get("robot")) + _payload(conditions.get("payload"))
            + _motion(conditions.get("motion")) + _cube(conditions.get("cube"), conditions.get("cycles"))
            + (_environment(conditions.get("environment")) if "environment" in conditions else "")
            + _warm_up(conditions.get("warm_up")) + _measurement_system(conditions.get("measurement_system"))
            + _sessions(conditions.get("sessions"))
            + (("<h3>Further conditions</h3>" + mapping_table(rest)) if rest else ""))


def _from_run(run: Mapping[str, Any]) -> list[tuple[str, str]]:
    """What a run stored before ``test_conditions`` existed still says about its conditions."""
    params, station, results = run.get("parameters") or {}, run.get("station") or {}, run.get("results") or {}
    envelope = station.get("envelope") or {}
    rows: list[tuple[str, str]] = [("robot", "<span class=muted>identity not recorded by this run</span> — station "
                                             + escape(str(run.get("station_name") or "?")))]
    if is_number(params.get("speed_percent")) and is_number(envelope.get("max_speed")):
        speed = envelope["max_speed"] * params["speed_percent"] / 100
        rows.append(("TCP speed", f"{speed * 1e3:.1f} mm/s ({params['speed_percent']:g} % of the station's "
                                  f"{envelope['max_speed'] * 1e3:.0f} mm/s limit)"))
    if is_number(params.get("acceleration_percent")) and is_number(envelope.get("max_acceleration")):
        acc = envelope["max_acceleration"] * params["acceleration_percent"] / 100
        rows.append(("TCP acceleration", f"{acc * 1e3:.0f} mm/s² ({params['acceleration_percent']:g} % of "
                                         f"{envelope['max_acceleration'] * 1e3:.0f} mm/s²)"))
    if "cube_edge_m" in params:
        centre = _mm(params.get("cube_center_m"))
        rows.append(("cube", f"edge {fmt(params['cube_edge_m'], 1e3, 1)} mm, centre ({centre}) mm in the measurement "
                             "frame M"))
    for label in results.get("order") or []:
        commanded = ((results.get("points") or {}).get(label) or {}).get("commanded")
        if isinstance(commanded, list) and len(commanded) >= 3:
            rows.append((f"{label} commanded", f"({_mm(commanded)}) mm, tool point in M after the transform step"))
    if is_number(params.get("settle_time_s")):
        rows.append(("settle time", f"{params['settle_time_s']:g} s"))
    for key in ("payload", "environment", "warm-up", "operator"):
        rows.append((key, "<span class=muted>not recorded by this run</span>"))
    return rows


def conditions_html(run: Mapping[str, Any]) -> str:
    """The test conditions section (ISO runs, and any run whose results record them)."""
    stored = _conditions(run)
    if stored:
        body, note = stored_conditions_html(stored), ""
    elif _judged_against_iso(run) and run.get("results"):
        body = key_value_table(_from_run(run))
        note = ("<p class=note>This run was stored before the test conditions were recorded; what its parameters "
                "and station snapshot say is shown.</p>")
    else:
        return ""
    system = [("station", escape(str(run.get("station_name") or "—"))),
              ("software", escape(str(run.get("software_version") or "—"))),
              ("calibration records in force", "<code class=hash>"
               + escape(str(run.get("calibration_record_id") or "none")) + "</code>"),
              ("measured", f"{local_time(run.get('started'))} – {local_time(run.get('finished'))}")]
    return ("<section class=part id=conditions><h2>Test conditions</h2>" + note + body
            + "<h3>Run</h3>" + key_value_table(system) + "</section>")
