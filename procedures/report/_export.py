"""A run's samples as CSV (SI columns, the unit in each name) and the whole run as JSON.

Both give the samples as they were committed (``Sample.as_stored``), whichever version committed them, so
an export of a stored run never changes with the code that reads it.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Sequence
from typing import Any

from procedures.store import Sample

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
    for sample in samples:
        s = sample.as_stored()
        commanded = (s["commanded"] or {}).get("tcp_pose") or [None] * 6
        solved = (s["solved"] or {}).get("pose") or [None] * 6
        corrected = (s["corrected"] or {}).get("pose") or [None] * 6
        ref = s["reference"] or {}
        writer.writerow([s["run_id"], s["step_index"], s["step_key"], s["phase"], s["label"], int(s["ok"]),
                         s["error"] or "", *commanded, *solved, *corrected, (s["solved"] or {}).get("residual_rms"),
                         ref.get("value"), ref.get("interferometer_m"), ref.get("table_rad"), s["t_start"],
                         s["t_measured"], s["t_committed"]])
    return out.getvalue()


def export_json(run: dict[str, Any], samples: Sequence[Sample], events: Sequence[dict[str, Any]],
                superseded: Sequence[Sample] = ()) -> str:
    """The run row, its samples, the failed samples measured again later, and its events as one JSON document."""
    return json.dumps({"run": run, "samples": [s.as_stored() for s in samples],
                       "superseded_samples": [s.as_stored() for s in superseded], "events": events},
                      indent=1, default=str)
