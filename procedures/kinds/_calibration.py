"""What the two calibration kinds share: the point grid and the analysis into a calibration record."""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from procedures._science import COMPONENTS
from procedures._store import Sample
from procedures.kinds._protocol import Analysis, AnalysisContext


def inclusive_range(start: float, stop: float, step: float) -> np.ndarray:
    """``start, start + step, ...`` up to and including ``stop`` (within rounding)."""
    count = int(np.floor((stop - start) / step + 1e-9)) + 1
    return start + step * np.arange(count)


def analyse_calibration(samples: Sequence[Sample], ctx: AnalysisContext, *, kind: str,
                        component_of_axis: Mapping[str, str], reference_instrument: str,
                        record_path: str | None) -> Analysis:
    """Fit a calibration record on the run's (measured, reference, group, point) rows and write it.

    Parameters
    ----------
    samples : the run's samples; failed ones and other phases are skipped
    ctx : the analysis context (science, run folder, truth of a simulated cell)
    kind : ``"displacement"`` or ``"angle"``: names the record file and the results
    component_of_axis : the pose component each axis calibrates (``{"x": "a"}`` for angles)
    reference_instrument : named in the record's provenance
    record_path : where to write the record; default ``<run folder>/calibration-<kind>.json``
    """
    data: dict[str, list[dict[str, Any]]] = {}
    for sample in samples:
        if not sample.ok or sample.phase != "calibration" or sample.meta is None or sample.solved is None:
            continue
        component = component_of_axis[sample.meta["axis"]]
        index = COMPONENTS.index(component)
        entry = {"group": sample.meta["group"], "repeat": sample.meta["repeat"], "point": sample.meta["point"],
                 "nominal": sample.meta["nominal"], "measured": sample.solved["pose"][index],
                 "reference": (sample.reference or {})["value"]}
        if ctx.truth is not None and sample.t_measured is not None:
            state = ctx.truth.at(sample.t_measured)
            if state is not None:
                true_pose = list(state["opr_in_m"]["t"]) + list(state["opr_in_m"]["euler"])
                entry["true"] = true_pose[index]
        data.setdefault(component, []).append(entry)
    if not data:
        raise ValueError("no successful calibration samples to fit")
    fit = ctx.science.fit_calibration(kind, data, {
        "run_id": ctx.run_id, "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "references": [{"instrument": reference_instrument, "components": sorted(data)}]})
    path = Path(record_path) if record_path else ctx.run_dir / f"calibration-{kind}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(fit.record_json, encoding="utf-8")
    results = {
        "kind": f"{kind}_calibration", "record_path": str(path.resolve()), "record_id": fit.record_id,
        "data": data, "curves": fit.curves, "summary": fit.summary,
        "failed_samples": sum(1 for s in samples if not s.ok),
    }
    return Analysis(results=results, calibration_record_id=fit.record_id)


def calibration_summary_lines(results: Mapping[str, Any]) -> list[str]:
    """``instrument show``: where the record went."""
    return [f"record     {results['record_path']} ({results['record_id']})"]
