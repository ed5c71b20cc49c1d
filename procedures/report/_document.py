"""One self-contained HTML report per run (screen and print from one file; the PDF renders the same).

Units are converted at this edge only: here and in the section modules (``_iso``, ``_calibration``,
``_dynamic``, ``_conditions``), which the registry (``_sections``) picks by the shape of a run's results
(see docs/report.md)."""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from html import escape
from typing import Any

from procedures.report._conditions import banner_html, conditions_html, name_note, report_title
from procedures.report._format import display_json, first_line, key_value_table
from procedures.report._sections import results_html
from procedures.report._style import stylesheet
from procedures.store import Sample


def _time(stamp: float | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(stamp)) if stamp else "—"


def _short(text: str | None, anchor: str) -> str:
    """A long text's first line and "…", pointing to its full text in the appendix."""
    line, cut = first_line(text or "")
    if not cut:
        return escape(line)
    return f"{escape(line)} … <small>(full text: <a href='#{anchor}'>appendix</a>)</small>"


def robot_label(run: Mapping[str, Any]) -> str:
    """Whose robot: the identity the run recorded (results or run row), else the station's name."""
    robot = ((run.get("results") or {}).get("test_conditions") or {}).get("robot")
    if isinstance(robot, Mapping):
        model = robot.get("model") or robot.get("robot_model")
        serial = robot.get("serial_number") or robot.get("serial")
        if model or serial:
            return " ".join(str(v) for v in (robot.get("manufacturer"), model) if v) + (f" s/n {serial}" if serial
                                                                                         else "")
    if run.get("robot_serial"):
        return f"{run.get('robot_model') or 'robot'} s/n {run['robot_serial']}"
    return f"station {run.get('station_name') or '?'}"


def _header_html(run: dict[str, Any], samples: Sequence[Sample]) -> str:
    ok = sum(1 for s in samples if s.ok)
    rows = [
        ("run", f"<code class=hash>{escape(run['id'])}</code>"),
        ("procedure", f"{escape(run['procedure'])} — {name_note(run)}"),
        ("state", f"{escape(str(run['state']))} ({escape(str(run.get('exit_status') or ''))})"),
    ]
    if run.get("reason"):
        rows.append(("reason", _short(str(run["reason"]), "appendix-reason")))
    rows += [
        ("robot", escape(robot_label(run))),
        ("station", escape(f"{run.get('station_name')}") + f" <small>{escape(str(run.get('station_path') or ''))}"
                    "</small>"),
        ("calibration record", f"<code class=hash>{escape(str(run.get('calibration_record_id') or 'none'))}</code>"),
        ("software", escape(str(run.get("software_version")))),
        ("created / started / finished",
         f"{_time(run['created'])} / {_time(run.get('started'))} / {_time(run.get('finished'))}"),
        ("samples", f"{ok} measured, {len(samples) - ok} failed, of {run.get('total_steps')} planned"),
        ("report generated", _time(time.time())),
    ]
    return key_value_table(rows)


def _failed_html(samples: Sequence[Sample], superseded: Sequence[Sample]) -> str:
    failed = [(s, "failed") for s in samples if not s.ok] + [(s, "measured again later") for s in superseded]
    if not failed:
        return ""
    rows = "".join(
        f"<tr><td class=l>{escape(s.step_key)}</td><td class=l>{escape(first_line(s.error or '')[0])}"
        f"{' …' if first_line(s.error or '')[1] else ''}</td><td class=l>{len(s.frames or [])} saved</td>"
        f"<td class=l>{then}</td></tr>" for s, then in failed)
    return ("<section id=failed><h2>Failed poses</h2><table><tr><th class=l>step</th><th class=l>error (first line; "
            "the full text is in the run log)</th><th class=l>frames</th><th class=l>then</th></tr>"
            f"{rows}</table></section>")


SIGN_OFF_ROLES = ("Prepared by", "Checked by", "Approved by")


def signoff_html() -> str:
    """Name, function, date and signature lines for the people who sign the result."""
    rows = "".join(f"<tr><th class=l>{role}</th><td></td><td></td><td></td><td class=sign></td></tr>"
                   for role in SIGN_OFF_ROLES)
    return ("<section class=signoff id=signoff><h2>Sign-off</h2>"
            "<p class=note>By signing, the reviewer confirms that the test conditions and deviations above were "
            "read and that the results stand as reported for the purpose stated.</p>"
            "<table class=signoff><tr><th class=l></th><th class=l>name</th><th class=l>function</th>"
            f"<th class=l>date</th><th class=l>signature</th></tr>{rows}</table></section>")


LIST_LIMIT = 12  # longer lists in the appendix's results are summarised (they are in the JSON export)


def _summarised(value: Any) -> Any:
    """``value`` with its long lists and its arrays of poses replaced by a count (they are in the export)."""
    if isinstance(value, Mapping):
        return {k: _summarised(v) for k, v in value.items()}
    if isinstance(value, list):
        if len(value) > LIST_LIMIT or (value and all(isinstance(v, list) for v in value)):
            return f"{len(value)} entries (instrument export RUN --json)"
        return [_summarised(v) for v in value]
    return value


# Results keys the sections render in full (docs/results.md); the appendix leaves them out.
SHOWN_ABOVE = ("figures", "uncertainty", "test_conditions", "deviations", "evaluation", "before_after",
               "residual_uncertainty", "reference_vs_truth")


def _appendix_html(run: dict[str, Any], events: Sequence[dict[str, Any]]) -> str:
    event_rows = "".join(f"<tr><td class=l>{_time(e['time'])}</td><td class=l>{escape(e['kind'])}</td>"
                         f"<td class=l><pre class=inline>{escape(e['message'] or '')}</pre></td></tr>"
                         for e in events if e["kind"] not in ("measure_failed",))
    reason = (f"<h3 id=appendix-reason>Reason (full text)</h3><pre>{escape(str(run['reason']))}</pre>"
              if run.get("reason") and first_line(str(run["reason"]))[1] else "")
    results = run.get("results")
    if isinstance(results, Mapping):
        results = {k: v for k, v in results.items() if k not in SHOWN_ABOVE}
        if isinstance(results.get("summary"), Mapping):  # its evaluation is the held-out table above
            results["summary"] = {k: v for k, v in results["summary"].items() if k != "evaluation"}
    return (
        "<section class=part id=appendix><h2>Appendix: provenance and raw data</h2>"
        "<p class=note>Values below are as stored, in SI units (m, rad, s), rounded to 9 significant digits for "
        "display; the results without what the sections above show in full (figures, uncertainty, test conditions, "
        "deviations, evaluations) and without the arrays of poses; all of it: <code>instrument export RUN --json"
        "</code>.</p>"
        f"{reason}"
        f"<h3>Parameters</h3><pre>{escape(display_json(run.get('parameters')))}</pre>"
        f"<h3>Procedure file</h3><pre>{escape(run.get('procedure_text') or '')}</pre>"
        f"<h3>Station snapshot</h3><pre>{escape(display_json(run.get('station')))}</pre>"
        + (f"<h3>Results</h3><pre>{escape(display_json(_summarised(results)))}</pre>" if results else "")
        + f"<h3>Events</h3><table class=events>{event_rows}</table></section>"
    )


def render_report(run: dict[str, Any], samples: Sequence[Sample], events: Sequence[dict[str, Any]],
                  superseded: Sequence[Sample] = ()) -> str:
    """The whole report as one HTML string (inline CSS and SVG, no scripts, no external resources).

    Parameters
    ----------
    run : the stored run row (``RunStore.get_run``), its ``results`` as the procedure kind stored them.
    samples, events : the run's samples and log.
    superseded : failed samples that a later session measured again (listed with the failed poses).

    Returns
    -------
    str
        The HTML document; its print stylesheet (A4, running headers, page numbers) is what
        ``procedures.report._pdf.render_pdf`` renders.
    """
    title = report_title(run)
    style = stylesheet(run_id=run["id"], procedure=str(run.get("procedure_name") or run["procedure"]),
                       robot=robot_label(run), title=title)
    body = (f"<h1>{escape(title)}</h1>{banner_html(run)}{_header_html(run, samples)}{results_html(run)}"
            f"{conditions_html(run)}{_failed_html(samples, superseded)}{signoff_html()}{_appendix_html(run, events)}")
    return (f"<!DOCTYPE html><html lang=en><head><meta charset='utf-8'><title>{escape(title)} — run {run['id'][:8]}"
            f"</title><style>{style}</style></head><body>{body}</body></html>")
