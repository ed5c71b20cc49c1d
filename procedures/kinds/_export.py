"""The normalised results of a run, as ``instrument export RUN --json`` carries them (docs/results.md, "Export").

One shape for every run: a figure object per point and characteristic (value, expanded_uncertainty,
coverage_factor, confidence_interval, true, unit, budget), the test conditions, the deviations and
the uncertainty's method and budget. Runs stored by older code (no ``results_version``) export their
figures from ``stats`` with no uncertainty.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from procedures.kinds.dynamic import DYNAMIC_KINDS, dynamic_figures
from procedures.kinds.iso import POINT_FIGURES, figure_without_uncertainty

SCHEMA = "opr-instrument-results/1"


def normalised_results(run: Mapping[str, Any]) -> dict[str, Any]:
    """The export's ``results`` object for a stored run (any kind, any age, finished or not)."""
    results = run.get("results") or {}
    kind = results.get("kind") or run.get("procedure")
    version = results.get("results_version")
    out: dict[str, Any] = {
        "schema": SCHEMA, "kind": kind, "points": {}, "distances": {}, "directions": {}, "components": {},
        "test_conditions": results.get("test_conditions"), "deviations": list(results.get("deviations") or []),
        "uncertainty": None,
        "stored_by": f"results_version {version}" if version else "older code (no uncertainty)",
    }
    if kind == "iso9283":
        figures = results.get("figures")
        if figures:
            out.update(points=figures.get("points", {}), distances=figures.get("distances", {}),
                       directions=figures.get("directions", {}))
        else:
            for label, entry in (results.get("points") or {}).items():
                stats = entry.get("stats")
                if stats:
                    true = entry.get("true_stats") or {}
                    out["points"][label] = {name: figure_without_uncertainty(name, stats, true)
                                            for name in POINT_FIGURES if name in stats}
        out["uncertainty"] = results.get("uncertainty")
    elif kind in DYNAMIC_KINDS:
        out["dynamic"] = dynamic_figures(results)
        out["uncertainty"] = results.get("uncertainty")
    elif isinstance(kind, str) and kind.endswith("_calibration"):
        out["components"] = dict(results.get("residual_uncertainty") or {})
    return out
