"""The durable run store: one SQLite database (WAL) in the runs folder.

A run row holds what was asked (procedure, parameters, station snapshot, software version,
calibration record in force) and how it ended (state, exit status, reason). A sample row holds one
measured pose with everything needed to recompute it. Every sample is committed (and therefore on
disk, WAL + ``synchronous=FULL``) before the engine sends the next motion, so a killed process
loses nothing it reported; ``(run_id, step_index)`` is the primary key, so a resumed run can never
write a step twice.
"""

from __future__ import annotations

import json
import os
import socket
import sqlite3
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from procedures._run_state import RunState

SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    id TEXT PRIMARY KEY,
    procedure TEXT NOT NULL,
    procedure_name TEXT,
    procedure_file TEXT,
    procedure_text TEXT,
    parameters TEXT NOT NULL,
    station_name TEXT,
    station_path TEXT,
    station TEXT NOT NULL,
    software_version TEXT,
    calibration_record_id TEXT,
    state TEXT NOT NULL,
    exit_status TEXT,
    reason TEXT,
    total_steps INTEGER,
    created REAL NOT NULL,
    started REAL,
    finished REAL,
    host TEXT,
    pid INTEGER,
    results TEXT
);
CREATE TABLE IF NOT EXISTS samples (
    run_id TEXT NOT NULL REFERENCES runs(id),
    step_index INTEGER NOT NULL,
    step_key TEXT NOT NULL,
    phase TEXT NOT NULL,
    label TEXT,
    ok INTEGER NOT NULL,
    error TEXT,
    commanded TEXT,
    solved TEXT,
    corrected TEXT,
    crosses TEXT,
    reference TEXT,
    meta TEXT,
    frames TEXT,
    t_start REAL,
    t_measured REAL,
    t_committed REAL,
    PRIMARY KEY (run_id, step_index)
);
CREATE TABLE IF NOT EXISTS events (
    run_id TEXT NOT NULL,
    time REAL NOT NULL,
    kind TEXT NOT NULL,
    message TEXT,
    data TEXT
);
"""

_JSON_RUN = ("parameters", "station", "results")
_JSON_SAMPLE = ("commanded", "solved", "corrected", "crosses", "reference", "meta", "frames")


def _dumps(value: Any) -> str | None:
    return None if value is None else json.dumps(value, default=_default, allow_nan=True)


def _default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot store {type(value).__name__}")


@dataclass
class Sample:
    """A sample as read back from the store (JSON fields decoded)."""

    run_id: str
    step_index: int
    step_key: str
    phase: str
    label: str | None
    ok: bool
    error: str | None
    commanded: dict | None
    solved: dict | None
    corrected: dict | None
    crosses: dict | None
    reference: dict | None
    meta: dict | None
    frames: list | None
    t_start: float | None
    t_measured: float | None
    t_committed: float | None


class RunStore:
    """The run database in ``runs_dir`` (``runs.sqlite``) plus a folder per run for files.

    One connection per store object, used from one thread at a time (the engine's).
    """

    def __init__(self, runs_dir: str | Path, *, timeout: float = 30.0) -> None:
        self.runs_dir = Path(runs_dir)
        self.runs_dir.mkdir(parents=True, exist_ok=True)
        self.path = self.runs_dir / "runs.sqlite"
        self._db = sqlite3.connect(self.path, timeout=timeout, isolation_level=None, check_same_thread=False)
        self._db.row_factory = sqlite3.Row
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")  # a commit is on disk when it returns
        self._db.executescript(SCHEMA)

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> RunStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def run_dir(self, run_id: str) -> Path:
        path = self.runs_dir / run_id
        path.mkdir(parents=True, exist_ok=True)
        return path

    # ------------------------------------------------------------------------------------ runs
    def create_run(
        self,
        *,
        procedure: str,
        parameters: dict,
        station: dict,
        software_version: str,
        procedure_name: str | None = None,
        procedure_file: str | None = None,
        procedure_text: str | None = None,
        station_name: str | None = None,
        station_path: str | None = None,
        calibration_record_id: str | None = None,
        total_steps: int | None = None,
    ) -> str:
        run_id = uuid.uuid4().hex
        self._db.execute(
            "INSERT INTO runs (id, procedure, procedure_name, procedure_file, procedure_text, parameters, "
            "station_name, station_path, station, software_version, calibration_record_id, state, total_steps, "
            "created) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
            (run_id, procedure, procedure_name, procedure_file, procedure_text, _dumps(parameters), station_name,
             station_path, _dumps(station), software_version, calibration_record_id, RunState.QUEUED.value,
             total_steps,
             time.time()),
        )
        self.log(run_id, "created", f"{procedure} queued")
        return run_id

    def set_state(self, run_id: str, state: RunState, *, reason: str | None = None) -> None:
        """Record a state change (and its exit status and reason) in the run row and its events."""
        state = RunState(state)  # a plain string from a caller is checked here
        now = time.time()
        sets = ["state = ?", "reason = ?", "exit_status = ?"]
        values: list[Any] = [state.value, reason, state.exit_status]
        if state == RunState.RUNNING:
            sets += ["started = COALESCE(started, ?)", "host = ?", "pid = ?", "finished = NULL"]
            values += [now, socket.gethostname(), os.getpid()]
        if state.ended:
            sets.append("finished = ?")
            values.append(now)
        self._db.execute(f"UPDATE runs SET {', '.join(sets)} WHERE id = ?", (*values, run_id))
        self.log(run_id, "state", state.value + (f": {reason}" if reason else ""))

    def set_results(self, run_id: str, results: dict) -> None:
        self._db.execute("UPDATE runs SET results = ? WHERE id = ?", (_dumps(results), run_id))

    def update_run(self, run_id: str, **fields: Any) -> None:
        allowed = {"calibration_record_id", "total_steps", "station", "station_path"}
        if not set(fields) <= allowed:
            raise ValueError(f"cannot update {sorted(set(fields) - allowed)}")
        for key, value in fields.items():
            self._db.execute(f"UPDATE runs SET {key} = ? WHERE id = ?",
                             (_dumps(value) if key == "station" else value, run_id))

    def get_run(self, run_id: str) -> dict[str, Any]:
        """The run row as a dict (JSON fields decoded, ``state`` a ``RunState``). ``run_id`` may be a unique prefix."""
        rows = self._db.execute("SELECT * FROM runs WHERE id LIKE ? ORDER BY created", (run_id + "%",)).fetchall()
        if not rows:
            raise KeyError(f"no run {run_id!r} in {self.path}")
        if len(rows) > 1:
            raise KeyError(f"run id prefix {run_id!r} is ambiguous ({len(rows)} runs); give more characters")
        run = dict(rows[0])
        for key in _JSON_RUN:
            run[key] = json.loads(run[key]) if run[key] else None
        run["state"] = RunState(run["state"])
        return run

    def list_runs(self) -> list[dict[str, Any]]:
        """Every run, oldest first: the run row's summary columns plus its number of samples."""
        rows = self._db.execute(
            "SELECT r.id, r.procedure, r.procedure_name, r.station_name, r.state, r.exit_status, r.reason, "
            "r.created, r.started, r.finished, r.total_steps, "
            "(SELECT COUNT(*) FROM samples s WHERE s.run_id = r.id) AS samples "
            "FROM runs r ORDER BY r.created"
        ).fetchall()
        return [{**dict(row), "state": RunState(row["state"])} for row in rows]

    # --------------------------------------------------------------------------------- samples
    def add_sample(
        self,
        run_id: str,
        step_index: int,
        step_key: str,
        phase: str,
        *,
        label: str | None = None,
        ok: bool = True,
        error: str | None = None,
        commanded: dict | None = None,
        solved: dict | None = None,
        corrected: dict | None = None,
        crosses: dict | None = None,
        reference: dict | None = None,
        meta: dict | None = None,
        frames: list | None = None,
        t_start: float | None = None,
        t_measured: float | None = None,
    ) -> None:
        """Insert and commit one sample. Raises ``sqlite3.IntegrityError`` if the step is
        already stored (a resumed run must never measure a committed step again)."""
        self._db.execute(
            "INSERT INTO samples (run_id, step_index, step_key, phase, label, ok, error, commanded, solved, "
            "corrected, crosses, reference, meta, frames, t_start, t_measured, t_committed) "
            "VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
            (run_id, step_index, step_key, phase, label, int(ok), error, _dumps(commanded), _dumps(solved),
             _dumps(corrected), _dumps(crosses), _dumps(reference), _dumps(meta), _dumps(frames), t_start,
             t_measured, time.time()),
        )

    def committed_steps(self, run_id: str) -> set[int]:
        rows = self._db.execute("SELECT step_index FROM samples WHERE run_id = ?", (run_id,)).fetchall()
        return {row[0] for row in rows}

    def samples(self, run_id: str) -> list[Sample]:
        rows = self._db.execute("SELECT * FROM samples WHERE run_id = ? ORDER BY step_index", (run_id,))
        return list(self._decode(rows))

    @staticmethod
    def _decode(rows: Iterator[sqlite3.Row]) -> Iterator[Sample]:
        for row in rows:
            data = dict(row)
            for key in _JSON_SAMPLE:
                data[key] = json.loads(data[key]) if data[key] else None
            data["ok"] = bool(data["ok"])
            yield Sample(**data)

    # ---------------------------------------------------------------------------------- events
    def log(self, run_id: str, kind: str, message: str = "", data: dict | None = None) -> None:
        self._db.execute("INSERT INTO events (run_id, time, kind, message, data) VALUES (?,?,?,?,?)",
                         (run_id, time.time(), kind, message, _dumps(data)))

    def events(self, run_id: str) -> list[dict]:
        rows = self._db.execute("SELECT time, kind, message, data FROM events WHERE run_id = ? ORDER BY rowid",
                                (run_id,)).fetchall()
        return [{**dict(row), "data": json.loads(row["data"]) if row["data"] else None} for row in rows]
