"""One self-contained HTML report per run, and CSV / JSON exports. Units are converted at this edge only
(here and in ``_report_sections``, which the procedure kinds use for their results)."""

from __future__ import annotations

import csv
import io
import json
import time
from collections.abc import Sequence
from dataclasses import asdict
from html import escape
from typing import Any

from procedures._store import Sample
from procedures.kinds import KINDS

_CSS = """body{font-family:sans-serif;margin:2em;max-width:1100px;color:#222}
table{border-collapse:collapse;margin:1em 0}th,td{border:1px solid #bbb;padding:3px 8px;text-align:right}
th{background:#eee}td.l,th.l{text-align:left}.true{color:#2a7a2a}.bad{color:#b00}
pre{background:#f6f6f6;padding:8px;overflow-x:auto;font-size:11px}.plots svg{margin:4px}"""


def _time(stamp: float | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(stamp)) if stamp else "—"


def _results_html(run: dict[str, Any]) -> str:
    """The results section, written by the run's procedure kind."""
    results = run.get("results")
    if not results:
        return "<p>No results: the run has not finished.</p>"
    kind = KINDS.get(run["procedure"])
    if kind is None:
        return f"<p>No report section for procedure {escape(run['procedure'])}: results only in the export.</p>"
    return kind.report_html(results)


def render_report(run: dict[str, Any], samples: Sequence[Sample], events: Sequence[dict[str, Any]],
                  superseded: Sequence[Sample] = ()) -> str:
    """The whole report as one HTML string (inline CSS and SVG, no external resources).

    ``superseded``: failed samples that a later session measured again (listed with the failed poses).
    """
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
    body = _results_html(run)
    failed = [(s, "failed") for s in samples if not s.ok] + [(s, "measured again later") for s in superseded]
    failed_html = (
        (
            "<h2>Failed poses</h2><table><tr><th class=l>step</th><th class=l>error</th><th class=l>frames</th>"
            "<th class=l>then</th></tr>"
            + "".join(
                f"<tr><td class=l>{escape(s.step_key)}</td><td class=l>{escape(s.error or '')}</td>"
                f"<td class=l>{len(s.frames or [])} saved</td><td class=l>{then}</td></tr>"
                for s, then in failed
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


def export_csv(samples: Sequence[Sample]) -> str:
    """One row per sample, SI columns with their units in the names."""
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


def export_json(run: dict[str, Any], samples: Sequence[Sample], events: Sequence[dict[str, Any]],
                superseded: Sequence[Sample] = ()) -> str:
    """The run row, its samples, the failed samples measured again later, and its events as one JSON document."""
    return json.dumps({"run": run, "samples": [asdict(s) for s in samples],
                       "superseded_samples": [asdict(s) for s in superseded], "events": events},
                      indent=1, default=str)
