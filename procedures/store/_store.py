"""The durable run store: one database (SQLite in the runs folder by default, or a shared PostgreSQL).

A run row holds what was asked (procedure, parameters, station snapshot, software version,
calibration record in force), on which robot (manufacturer, model, serial, controller version, read
from the controller) and how it ended (state, exit status, reason). A sample row holds one measured
pose with everything needed to recompute it. Every sample is committed (on disk: SQLite WAL +
``synchronous=FULL``, PostgreSQL's own commit) before the engine sends the next motion, so a killed
process loses nothing it reported; ``(run_id, step_index)`` is the primary key, so a resumed run can
never write a step twice. A failed sample is the one exception: a later session measures its step
again, and the failed row moves to ``superseded_samples`` in the same transaction (kept, never lost).

Exclusivity: a process that runs a run holds its **lease** (a row in ``leases`` with the pid, the
host and a random token), checked and taken in one transaction (SQLite: ``BEGIN IMMEDIATE``;
PostgreSQL: under an advisory lock on the run id). A second process is refused while the holder
lives; a lease whose process is gone is taken over. Every state change is a compare-and-set on the
state the engine last saw *and* on its lease token (PostgreSQL: the lease row held ``FOR SHARE``
meanwhile, so a take-over waits for it), so a process that lost its lease can never flip a run's state.

The databases themselves (connection, placeholders, transactions, the change counter) are in
``procedures.store._db``; the schema and its versioned migrations in ``procedures.store._schema``.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import time
import uuid
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from procedures.station import RunLocked, StateConflict
from procedures.store._db import (
    SQLITE_FILE,
    Database,
    DuplicateStep,
    StoreError,
    StoreTrouble,
    connect,
    store_location,
    store_timeout,
)
from procedures.store._run_state import RunState
from procedures.store._samples import SAMPLE_FIELDS, Reference, Sample
from procedures.store._sessions import SessionConditions

__all__ = ["ROBOT_COLUMNS", "DuplicateStep", "Lease", "RunStore", "StoreError", "StoredStream"]

ROBOT_COLUMNS = ("robot_manufacturer", "robot_model", "robot_serial", "robot_controller_version")

_SAMPLE_COLUMNS = ", ".join(SAMPLE_FIELDS)

FOREIGN_LEASE_TTL_S = 600.0
"""A lease held from another host counts as stale when not renewed for this long (the engine renews
it at every step; a lease of this host is judged by whether its process still lives)."""


def _process_start(pid: int) -> str | None:
    """The kernel's start time of process ``pid`` (Linux ``/proc``), to tell a reused pid; None if unknown."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as handle:
            fields = handle.read().rsplit(")", 1)[1].split()
        return fields[19]  # field 22 of stat(5), counted after the command name
    except (OSError, IndexError):
        return None


def _alive(pid: int, process_start: str | None) -> bool:
    """Whether the process that took a lease on this host still runs."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # it exists, owned by someone else
    now_start = _process_start(pid)
    return process_start is None or now_start is None or now_start == process_start


@dataclass(frozen=True)
class Lease:
    """This process's right to run one run (see the module docstring)."""

    run_id: str
    token: str
    taken_over: dict[str, Any] | None = None  # the stale holder it replaced, if any

_JSON_RUN = ("parameters", "station", "results")
_JSON_SAMPLE = ("commanded", "solved", "corrected", "crosses", "reference", "meta", "frames")


def _dumps(value: Any) -> str | None:
    return None if value is None else json.dumps(value, default=_default, allow_nan=True)


def _default(value: Any) -> Any:
    np = sys.modules.get("numpy")  # a numpy value means numpy is loaded: reading the store never loads it
    if np is not None and isinstance(value, np.ndarray):
        return value.tolist()
    if np is not None and isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot store {type(value).__name__}")


@dataclass(frozen=True)
class StoredStream:
    """The pose stream of one step (a move measured in motion), as the store keeps it: one row.

    ``data`` is opaque to the store (``procedures.kinds._stream`` encodes and decodes it);
    ``format`` names the encoding, ``samples`` the rows, ``columns`` their names, ``meta`` the
    JSON-able rest (rate, drops, the robot's done time ...).
    """

    format: str
    samples: int
    columns: list[str]
    data: bytes
    meta: dict[str, Any] | None = None




class RunStore:
    """The run database plus a folder per run for files (``runs_dir/<run id>/``).

    Parameters
    ----------
    runs_dir : the runs folder: per-run files, and the SQLite database ``runs.sqlite`` by default
    url : a ``postgresql://`` URL for a store shared by many cells; default ``$INSTRUMENT_STORE``, and
        when that is unset or empty the runs folder's SQLite file. The per-run files stay in ``runs_dir``.
    timeout : seconds to wait for a lock or a connection; default ``$INSTRUMENT_STORE_TIMEOUT``, else 30

    One connection per store object, used from one thread at a time (the engine's). Opening a store
    migrates it to the latest schema version (``procedures.store._schema``).
    """

    def __init__(self, runs_dir: str | Path, *, url: str | None = None, timeout: float | None = None) -> None:
        self.runs_dir = Path(runs_dir)
        self.url = store_location(url)
        if self.url is None and not self.runs_dir.is_dir():
            try:
                self.runs_dir.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise StoreError(f"cannot make the runs folder {self.runs_dir}: {exc.strerror or exc}") from None
        self.timeout = store_timeout() if timeout is None else timeout
        """Seconds a statement waits for another process's lock before ``StoreLocked``."""
        self._db: Database = connect(self.runs_dir, self.url, timeout=self.timeout)
        self.dialect = self._db.dialect
        self.location = self._db.location
        """Where the store is, for messages: the SQLite file, or the URL without its password."""
        self.path = self.runs_dir / SQLITE_FILE
        self.read_only: bool = bool(getattr(self._db, "read_only", False))
        """Opened read-only (the folder or the file cannot be written): every write is a ``StoreReadOnly``."""

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> RunStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def check_writable(self) -> None:
        """Take the write lock and give it back at once: ``StoreReadOnly``, ``StoreLocked`` (after the busy
        timeout) ... before a command starts anything it would then have to stop."""
        with self._db.transaction():
            pass

    def make_room(self) -> bool:
        """Give back the room the SQLite store keeps in reserve (see ``RESERVE_BYTES``), so that a run the full
        disk stopped can still record its pause; whether there was any. Refilled the next time it is opened."""
        return self._db.release_reserve()

    def run_dir(self, run_id: str) -> Path:
        """The run's folder (made if missing; on a read-only runs folder it may not exist, and a write there
        is the writer's one-line error)."""
        path = self.runs_dir / run_id
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError:
            if not self.read_only:
                raise
        return path

    def version(self) -> int:
        """A number that changes when another connection commits a change (SQLite's ``data_version``;
        PostgreSQL: the ``store_changes`` counter, bumped by any change of runs, samples or events)."""
        return self._db.version()

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
             total_steps, time.time()),
        )
        self.log(run_id, "created", f"{procedure} queued")
        return run_id

    def set_state(self, run_id: str, state: RunState, *, reason: str | None = None,
                  expected: RunState | Iterable[RunState] | None = None, lease: Lease | None = None) -> None:
        """Record a state change (and its exit status and reason) in the run row and its events.

        Parameters
        ----------
        expected : the state(s) the caller believes the run is in; the change happens only if it
            still is (compare-and-set), else ``StateConflict``
        lease : the caller's lease; the change happens only while the caller still holds it
        """
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
        where, args = ["id = ?"], [run_id]
        if expected is not None:
            allowed = [RunState(expected)] if isinstance(expected, str) else [RunState(e) for e in expected]
            where.append(f"state IN ({', '.join('?' * len(allowed))})")
            args += [e.value for e in allowed]
        if lease is not None:
            where.append("EXISTS (SELECT 1 FROM leases WHERE leases.run_id = runs.id AND leases.token = ?)")
            args.append(lease.token)
        update = f"UPDATE runs SET {', '.join(sets)} WHERE {' AND '.join(where)}"
        if lease is not None and self.dialect != "sqlite":
            # The lease row is held FOR SHARE until the update commits: a take-over (which rewrites that
            # row) waits for it, so the check and the change cannot be split by another process.
            with self._db.transaction():
                self._db.rows("SELECT 1 FROM leases WHERE run_id = ? AND token = ? FOR SHARE", (run_id, lease.token))
                changed = self._db.execute(update, (*values, *args))
        else:
            changed = self._db.execute(update, (*values, *args))  # one statement: atomic on SQLite
        if changed != 1:
            now_state = self._db.rows("SELECT state FROM runs WHERE id = ?", (run_id,))
            holder = "" if lease is None or self._holds(lease) else "; this process no longer holds the run's lease"
            raise StateConflict(f"run {run_id}: cannot set {state.value}: it is "
                                f"{now_state[0]['state'] if now_state else 'gone'}{holder} (changed by another "
                                "process?)")
        try:
            self.log(run_id, "state", state.value + (f": {reason}" if reason else ""))
        except StoreTrouble:
            pass  # a full or locked store: the state (and its reason) is in the run row, only the event is missing

    # ---------------------------------------------------------------------------------- leases
    def acquire_lease(self, run_id: str) -> Lease:
        """Take the run's lease for this process, atomically; a stale lease (its process gone) is taken over.

        Raises
        ------
        RunLocked
            Another live process holds it (the message names its pid, host and since when).
        """
        host, pid, token = socket.gethostname(), os.getpid(), uuid.uuid4().hex
        now = time.time()
        with self._db.transaction(lock=f"lease:{run_id}"):  # check and take are one atomic step
            rows = self._db.rows("SELECT * FROM leases WHERE run_id = ?", (run_id,))
            previous = rows[0] if rows else None
            if previous is not None and self._lease_alive(previous):
                since = time.strftime("%H:%M:%S", time.localtime(previous["acquired"]))
                raise RunLocked(f"run {run_id} is already being run by pid {previous['pid']} on "
                                f"{previous['host']} (since {since}); wait for it to end or stop that process")
            self._db.execute(
                "INSERT INTO leases (run_id, token, host, pid, process_start, acquired, renewed) "
                "VALUES (?,?,?,?,?,?,?) ON CONFLICT (run_id) DO UPDATE SET token = excluded.token, "
                "host = excluded.host, pid = excluded.pid, process_start = excluded.process_start, "
                "acquired = excluded.acquired, renewed = excluded.renewed",
                (run_id, token, host, pid, _process_start(pid), now, now))
        if previous is not None:
            stale = {key: previous[key] for key in ("pid", "host", "acquired")}
            self.log(run_id, "lease_taken_over",
                     f"stale lease of pid {previous['pid']} on {previous['host']} taken over", stale)
        return Lease(run_id, token, previous)

    def renew_lease(self, lease: Lease) -> None:
        """Mark the lease as alive now (matters only for a store shared between hosts)."""
        self._db.execute("UPDATE leases SET renewed = ? WHERE run_id = ? AND token = ?",
                         (time.time(), lease.run_id, lease.token))

    def release_lease(self, lease: Lease) -> None:
        """Give the lease back (only if still ours)."""
        self._db.execute("DELETE FROM leases WHERE run_id = ? AND token = ?", (lease.run_id, lease.token))

    def lease_holder(self, run_id: str) -> dict[str, Any] | None:
        """The live process holding the run's lease (pid, host, acquired ...), or None."""
        rows = self._db.rows("SELECT * FROM leases WHERE run_id = ?", (run_id,))
        return rows[0] if rows and self._lease_alive(rows[0]) else None

    def _holds(self, lease: Lease) -> bool:
        return bool(self._db.rows("SELECT 1 AS held FROM leases WHERE run_id = ? AND token = ?",
                                  (lease.run_id, lease.token)))

    @staticmethod
    def _lease_alive(row: dict[str, Any]) -> bool:
        if row["host"] == socket.gethostname():
            return _alive(int(row["pid"]), row["process_start"])
        return time.time() - float(row["renewed"]) < FOREIGN_LEASE_TTL_S

    def set_results(self, run_id: str, results: dict) -> None:
        self._db.execute("UPDATE runs SET results = ? WHERE id = ?", (_dumps(results), run_id))

    def update_run(self, run_id: str, **fields: Any) -> None:
        """Change some columns of a run: the calibration record id, the plan's size, the station, the robot."""
        allowed = {"calibration_record_id", "total_steps", "station", "station_path", *ROBOT_COLUMNS}
        if not set(fields) <= allowed:
            raise ValueError(f"cannot update {sorted(set(fields) - allowed)}")
        for key, value in fields.items():
            self._db.execute(f"UPDATE runs SET {key} = ? WHERE id = ?",
                             (_dumps(value) if key == "station" else value, run_id))

    def get_run(self, run_id: str) -> dict[str, Any]:
        """The run row as a dict (JSON fields decoded, ``state`` a ``RunState``).

        ``run_id`` is the id, or a unique prefix of it (compared as plain text: no wildcards).
        """
        if not run_id:
            raise KeyError("no run id given")
        rows = self._db.rows("SELECT * FROM runs WHERE id = ?", (run_id,))
        if not rows:
            rows = self._db.rows("SELECT * FROM runs WHERE substr(id, 1, ?) = ? ORDER BY created",
                                 (len(run_id), run_id))
        if not rows:
            raise KeyError(f"no run {run_id!r} in {self.location}")
        if len(rows) > 1:
            raise KeyError(f"run id prefix {run_id!r} is ambiguous ({len(rows)} runs); give more characters")
        run = rows[0]
        for key in _JSON_RUN:
            run[key] = json.loads(run[key]) if run[key] else None
        run["state"] = RunState(run["state"])
        return run

    def list_runs(self, *, states: Iterable[RunState] = (), procedure: str | None = None,
                  procedures: Iterable[str] | None = None, robot: str | None = None,
                  last: int | None = None) -> list[dict[str, Any]]:
        """Runs, oldest first: the run row's summary columns plus its number of samples.

        Parameters
        ----------
        states : only runs in one of these states (all when empty)
        procedure : only runs of this procedure kind (e.g. ``iso9283_repeatability``)
        procedures : only runs of one of these kinds (none when empty)
        robot : only runs on the robot with this serial number
        last : only the newest ``last`` of those
        """
        where: list[str] = []
        args: list[Any] = []
        wanted = [RunState(state).value for state in states]
        if wanted:
            where.append(f"r.state IN ({', '.join('?' * len(wanted))})")
            args += wanted
        if procedure is not None:
            where.append("r.procedure = ?")
            args.append(procedure)
        if procedures is not None:
            kinds = list(procedures)
            where.append(f"r.procedure IN ({', '.join('?' * len(kinds))})" if kinds else "1 = 0")
            args += kinds
        if robot is not None:
            where.append("r.robot_serial = ?")
            args.append(robot)
        query = (
            "SELECT r.id, r.procedure, r.procedure_name, r.station_name, r.state, r.exit_status, r.reason, "
            "r.created, r.started, r.finished, r.total_steps, r.robot_manufacturer, r.robot_model, r.robot_serial, "
            "r.robot_controller_version, (SELECT COUNT(*) FROM samples s WHERE s.run_id = r.id) AS samples "
            "FROM runs r" + (f" WHERE {' AND '.join(where)}" if where else "") + " ORDER BY r.created DESC, r.id")
        if last is not None:
            query += " LIMIT ?"
            args.append(max(int(last), 0))
        rows = self._db.rows(query, args)
        return [{**row, "samples": int(row["samples"]), "state": RunState(row["state"])} for row in reversed(rows)]

    def robot_runs(self, serial: str, *, procedure: str | None = None, procedures: Iterable[str] | None = None,
                   states: Iterable[RunState] = (RunState.FINISHED,)) -> list[dict[str, Any]]:
        """Every run on the robot with serial number ``serial`` (whole rows, results decoded), oldest first."""
        return [self.get_run(row["id"]) for row in self.list_runs(states=states, procedure=procedure,
                                                                  procedures=procedures, robot=serial)]

    def parameters_of(self) -> dict[str, dict[str, Any]]:
        """Every run's parameters in force (``--set`` included), by run id: what a list of runs titles them by."""
        return {row["id"]: json.loads(row["parameters"]) for row in self._db.rows("SELECT id, parameters FROM runs")}

    def robots(self) -> list[dict[str, Any]]:
        """The robots the store has runs of: serial, manufacturer, model, number of runs, first and last run time."""
        return self._db.rows(
            "SELECT robot_serial AS serial, MAX(robot_manufacturer) AS manufacturer, MAX(robot_model) AS model, "
            "COUNT(*) AS runs, MIN(created) AS first, MAX(created) AS last FROM runs "
            "WHERE robot_serial IS NOT NULL GROUP BY robot_serial ORDER BY robot_serial")

    # --------------------------------------------------------------------------------- samples
    def add_sample(self, sample: Sample, *, stream: StoredStream | None = None,
                   session: SessionConditions | None = None) -> None:
        """Insert and commit one sample, with its pose ``stream`` and the ``session``'s test conditions (the
        first sample of a session that records them) in the same transaction; ``t_committed`` is now.

        A step stored as *failed* is measured again by a later session: its failed row moves to
        ``superseded_samples`` in the same transaction (a stream it had is replaced). Raises
        ``DuplicateStep`` if the step is already stored as measured (a resumed run must never measure
        such a step again).
        """
        row = {**sample.to_row(), "ok": int(sample.ok), "t_committed": time.time()}
        if sample.reference == Reference():
            row["reference"] = None  # nothing read beside the pose
        values = tuple(_dumps(row[key]) if key in _JSON_SAMPLE else row[key] for key in SAMPLE_FIELDS)
        run_id, step_index = sample.run_id, sample.step_index
        with self._db.transaction():
            self._db.execute(
                f"INSERT INTO superseded_samples ({_SAMPLE_COLUMNS}, superseded) SELECT {_SAMPLE_COLUMNS}, ? "
                "FROM samples WHERE run_id = ? AND step_index = ? AND ok = 0", (time.time(), run_id, step_index))
            self._db.execute("DELETE FROM samples WHERE run_id = ? AND step_index = ? AND ok = 0", (run_id, step_index))
            self._db.execute(f"INSERT INTO samples ({_SAMPLE_COLUMNS}) VALUES ({', '.join('?' * len(values))})",
                             values)
            if session is not None:
                self._db.execute("INSERT INTO session_conditions (run_id, started, conditions) VALUES (?,?,?)",
                                 (run_id, session.started, _dumps(session.to_stored())))
            if stream is not None:
                self._db.execute("DELETE FROM streams WHERE run_id = ? AND step_index = ?", (run_id, step_index))
                self._db.execute("INSERT INTO streams (run_id, step_index, format, samples, columns, meta, data) "
                                 "VALUES (?,?,?,?,?,?,?)", (run_id, step_index, stream.format, int(stream.samples),
                                                            _dumps(list(stream.columns)), _dumps(stream.meta),
                                                            bytes(stream.data)))

    def streams(self, run_id: str, steps: Iterable[int] | None = None) -> dict[int, StoredStream]:
        """The stored pose streams of a run by step index (of ``steps`` only, when given)."""
        sql = "SELECT step_index, format, samples, columns, meta, data FROM streams WHERE run_id = ?"
        params: list[Any] = [run_id]
        if steps is not None:
            wanted = sorted({int(s) for s in steps})
            if not wanted:
                return {}
            sql += f" AND step_index IN ({', '.join('?' * len(wanted))})"
            params += wanted
        out = {}
        for row in self._db.rows(sql + " ORDER BY step_index", params):
            index = int(row["step_index"])
            out[index] = StoredStream(format=row["format"], samples=int(row["samples"]),
                                      columns=json.loads(row["columns"]), data=bytes(row["data"]),
                                      meta=json.loads(row["meta"]) if row["meta"] else None)
        return out

    def stream_steps(self, run_id: str) -> list[int]:
        """The steps of a run that have a stored pose stream, in order (without reading the streams)."""
        return [int(r["step_index"]) for r in self._db.rows(
            "SELECT step_index FROM streams WHERE run_id = ? ORDER BY step_index", (run_id,))]

    def committed_steps(self, run_id: str) -> set[int]:
        """Steps with a stored sample, measured or failed."""
        return {int(row["step_index"]) for row in
                self._db.rows("SELECT step_index FROM samples WHERE run_id = ?", (run_id,))}

    def measured_steps(self, run_id: str) -> set[int]:
        """Steps stored as measured (``ok``): the ones a resumed run skips; failed ones are measured again."""
        return {int(row["step_index"]) for row in
                self._db.rows("SELECT step_index FROM samples WHERE run_id = ? AND ok = 1", (run_id,))}

    def superseded_samples(self, run_id: str) -> list[Sample]:
        """Failed samples that a later session measured again, oldest first."""
        return self._decode(self._db.rows(f"SELECT {_SAMPLE_COLUMNS} FROM superseded_samples WHERE run_id = ? "
                                          "ORDER BY superseded, step_index", (run_id,)))

    def samples(self, run_id: str) -> list[Sample]:
        return self._decode(self._db.rows(f"SELECT {_SAMPLE_COLUMNS} FROM samples WHERE run_id = ? "
                                          "ORDER BY step_index", (run_id,)))

    def sessions(self, run_id: str, *, earlier: bool = True) -> list[SessionConditions]:
        """The test conditions of each session of the run, oldest first: the run-level records (schema version
        6 on) and, with ``earlier``, those that earlier versions kept in a session's first sample
        (``reference["session"]``)."""
        found = [SessionConditions.from_stored(json.loads(row["conditions"])) for row in self._db.rows(
            "SELECT conditions FROM session_conditions WHERE run_id = ? ORDER BY started", (run_id,))]
        if earlier:
            for row in self._db.rows("SELECT reference FROM samples WHERE run_id = ? AND reference LIKE ? "
                                     "ORDER BY step_index", (run_id, '%"session"%')):
                legacy = (json.loads(row["reference"]) or {}).get("session")
                if isinstance(legacy, Mapping):
                    found.append(SessionConditions.from_stored(legacy))
        return sorted(found, key=lambda s: s.started)

    @staticmethod
    def _decode(rows: list[dict[str, Any]]) -> list[Sample]:
        samples = []
        for data in rows:
            for key in _JSON_SAMPLE:
                data[key] = json.loads(data[key]) if data[key] else None
            data["ok"] = bool(data["ok"])
            samples.append(Sample.from_row(data))
        return samples

    # ---------------------------------------------------------------------------------- events
    def log(self, run_id: str, kind: str, message: str = "", data: dict | None = None) -> None:
        self._db.execute("INSERT INTO events (run_id, time, kind, message, data) VALUES (?,?,?,?,?)",
                         (run_id, time.time(), kind, message, _dumps(data)))

    def events(self, run_id: str) -> list[dict]:
        rows = self._db.rows("SELECT time, kind, message, data FROM events WHERE run_id = ? ORDER BY id", (run_id,))
        return [{**row, "data": json.loads(row["data"]) if row["data"] else None} for row in rows]
