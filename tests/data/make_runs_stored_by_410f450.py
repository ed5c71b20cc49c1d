"""Writes ``runs_stored_by_410f450.sql`` and ``runs_stored_by_410f450.outputs.json`` (see ``test_stored_runs.py``).

Runs against commit 410f450 only (the procedures package before it became subpackages, whose modules it
imports by their old private paths): ``git worktree add /tmp/at410f450 410f450`` and, from that folder,
``python /path/to/this/script.py OUTPUT_DIR``. It runs, on the fake cell (``tests.fakes``):

- a displacement and an angle calibration, finished (their records then put in force);
- an ISO 9283 run with both records in force (its cube inside their ranges), the truth log, a payload and
  an operator, paused after 8 poses and resumed to the end in a second session (two session records);
- an ISO 9283 run, a displacement and an angle calibration each left PAUSED (resumed by the test);
- a stabilisation and a path run (streams), finished;

then dumps the SQLite store as SQL, and records what ``runs``, ``show``, ``report``, ``export --csv``,
``export --json [--streams]``, ``history`` and the web view's run and history API gave for each run at
that commit, as SHA-256 digests of their bytes (the report's "report generated" time blanked).
"""

from __future__ import annotations

import importlib.util
import json
import sqlite3
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path.cwd()
sys.path.insert(0, str(ROOT))

from procedures._api import open_engine  # noqa: E402  (runs against 410f450: its private names)
from tests.fakes import FakeCell, FakeScience, write_station  # noqa: E402

# The outputs are taken by this checkout's tests/stored_outputs.py (only public names: the same at both commits).
_spec = importlib.util.spec_from_file_location("stored_outputs", Path(__file__).resolve().parents[1]
                                               / "stored_outputs.py")
assert _spec is not None and _spec.loader is not None
stored_outputs = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(stored_outputs)

NAME = "runs_stored_by_410f450"
FAST = {"settle_time_s": 0, "frames_per_pose": 1, "retry_backoff_s": 0}
DYNAMIC = {"cycles": 2, "speeds_percent": [100, 20], "rate_hz": 50.0, "rest_s": 0.0, "cube_edge_m": 0.04,
           "cube_center_m": [0.0, 0.0, 0.0], "min_poses": 8}
PROCEDURES = {
    "displacement": ("displacement_calibration", {"axes": ["x", "z"], "stop_mm": 20, "repeats": 2, "groups": 1,
                                                  "group_start_offsets_mm": [[0, 0, 0]],
                                                  "interferometer_average_s": 0.01}),
    "angle": ("angle_calibration", {"axes": ["z"], "step_deg": 0.5, "repeats": 2, "groups": 1,
                                    "group_start_offsets_deg": [0.0]}),
    "iso": ("iso9283_repeatability", {"cycles": 3, "cube_center_m": [0.01, 0.01, 0.01], "cube_edge_m": 0.01,
                                      "payload_mass_kg": 2.5, "operator": "A. Tester",
                                      "warm_up_s": 600, "uncertainty_draws": 0,
                                      "frames_per_pose": 2}),
    "iso_paused": ("iso9283_repeatability", {"cycles": 3, "cube_edge_m": 0.05}),
    "stabilisation": ("iso9283_stabilisation", {**DYNAMIC, "window_s": 0.3, "band_um": 10.0}),
    "path": ("iso9283_path", {**DYNAMIC, "hold_s": 0.1, "transform_step": False, "circle_radius_mm": 5.0,
                              "calculation_points": 5}),
}


def _procedure(folder: Path, key: str) -> Path:
    kind, parameters = PROCEDURES[key]
    path = folder / f"{key}.yaml"
    body = {"procedure": kind, "name": f"{key} (fixture)",
            "parameters": parameters if kind.startswith("iso9283_") and kind != "iso9283_repeatability"
            else {**FAST, **parameters}}
    path.write_text(yaml.safe_dump(body, sort_keys=False), encoding="utf-8")
    return path


def _run(runs: Path, station: Path, cell: FakeCell, procedure: Path | None = None, *, run_id: str | None = None,
         pause_after: int | None = None) -> str:
    """One session; ``pause_after``: paused after that many committed samples and left PAUSED."""
    engine_box = {}

    def listener(event: dict) -> None:
        if pause_after is not None and event["event"] == "progress" and event["done"] == pause_after:
            engine_box["engine"].request_pause("end of shift")

    with open_engine(runs, procedure=procedure, station=station if run_id is None else None, run_id=run_id,
                     science=FakeScience(cell), devices=cell.devices(), operator=cell.operator, listener=listener,
                     pause_handler=lambda engine: "detach") as engine:
        engine_box["engine"] = engine
        state = engine.execute()
        print(engine.run_id, state, file=sys.stderr)
        return engine.run_id


def main_(out_dir: Path) -> None:
    with tempfile.TemporaryDirectory() as scratch_name:
        scratch = Path(scratch_name)
        runs = scratch / "runs"
        truth = scratch / "truth.jsonl"
        station = write_station(scratch / "station.yaml", truth_log=str(truth))
        cell = FakeCell(seed=21, truth_log=truth)
        displacement = _run(runs, station, cell, _procedure(scratch, "displacement"))
        angle = _run(runs, station, cell, _procedure(scratch, "angle"))
        with sqlite3.connect(runs / "runs.sqlite") as db:
            records = [json.loads(db.execute("SELECT results FROM runs WHERE id = ?", (i,)).fetchone()[0])
                       ["record_path"] for i in (displacement, angle)]
        calibrated = write_station(scratch / "calibrated.yaml", truth_log=str(truth), calibration={"record": records})
        iso = _run(runs, calibrated, cell, _procedure(scratch, "iso"), pause_after=8)
        cell = FakeCell(seed=22, truth_log=truth)
        _run(runs, calibrated, cell, run_id=iso)
        _run(runs, station, FakeCell(seed=23), _procedure(scratch, "iso_paused"), pause_after=7)
        _run(runs, station, FakeCell(seed=24), _procedure(scratch, "displacement"), pause_after=7)
        _run(runs, station, FakeCell(seed=25), _procedure(scratch, "angle"), pause_after=7)
        for key in ("stabilisation", "path"):
            cell = FakeCell(seed=26)
            cell.timed_moves = True
            _run(runs, station, cell, _procedure(scratch, key))
        time.sleep(0.1)
        with sqlite3.connect(runs / "runs.sqlite") as db:
            db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            dump = "\n".join(db.iterdump()) + "\n"
        (out_dir / f"{NAME}.sql").write_text(dump, encoding="utf-8")
        # The outputs from the dump itself, in a fresh folder, exactly as the test loads it.
        again = scratch / "again"
        again.mkdir()
        db = sqlite3.connect(again / "runs.sqlite")
        db.executescript(dump)
        db.close()
        produced = stored_outputs.outputs(again, scratch)
    digests = {name: stored_outputs.digest(body) for name, body in produced.items()}
    (out_dir / f"{NAME}.outputs.json").write_text(json.dumps(digests, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main_(Path(sys.argv[1]).resolve())
