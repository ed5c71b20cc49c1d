"""The run store's schema and its versioned migrations, for SQLite and PostgreSQL.

One logical schema on both backends; each migration is written in each dialect (PostgreSQL's
``DOUBLE PRECISION`` where SQLite says ``REAL``, ``BIGSERIAL`` for the events' number). The
version a store is at is the highest row of its ``schema_version`` table; a store opened by newer
code is migrated in place, each migration in one transaction with its ``schema_version`` row, so a
crash leaves it at one version or the next, never between.

SQLite stores written before versioning (commit 5786d73 and later) have no ``schema_version``: their
version is read off their tables (``runs`` only: 1; with ``superseded_samples`` and ``leases``: 2).
JSON columns stay ``TEXT`` on both backends: a sample may hold NaN, which PostgreSQL's ``jsonb`` refuses.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Migration:
    """One step of the schema: ``version`` is what the store is at once it is applied."""

    version: int
    description: str
    sqlite: str
    postgresql: str

    def script(self, dialect: str) -> str:
        return self.sqlite if dialect == "sqlite" else self.postgresql


def _v1(real: str) -> str:
    return f"""
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
    created {real} NOT NULL,
    started {real},
    finished {real},
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
    t_start {real},
    t_measured {real},
    t_committed {real},
    PRIMARY KEY (run_id, step_index)
);
CREATE TABLE IF NOT EXISTS events (
    run_id TEXT NOT NULL,
    time {real} NOT NULL,
    kind TEXT NOT NULL,
    message TEXT,
    data TEXT
);
"""


def _v2(real: str) -> str:
    return f"""
CREATE TABLE IF NOT EXISTS superseded_samples (
    run_id TEXT NOT NULL,
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
    t_start {real},
    t_measured {real},
    t_committed {real},
    superseded {real} NOT NULL
);
CREATE TABLE IF NOT EXISTS leases (
    run_id TEXT PRIMARY KEY,
    token TEXT NOT NULL,
    host TEXT NOT NULL,
    pid INTEGER NOT NULL,
    process_start TEXT,
    acquired {real} NOT NULL,
    renewed {real} NOT NULL
);
"""


_ROBOT_COLUMNS = """
ALTER TABLE runs ADD COLUMN robot_manufacturer TEXT;
ALTER TABLE runs ADD COLUMN robot_model TEXT;
ALTER TABLE runs ADD COLUMN robot_serial TEXT;
ALTER TABLE runs ADD COLUMN robot_controller_version TEXT;
CREATE INDEX IF NOT EXISTS runs_robot_serial ON runs (robot_serial, created);
CREATE INDEX IF NOT EXISTS superseded_samples_run ON superseded_samples (run_id);
"""

# SQLite numbered its events by rowid; a column of their own (the same numbers) is what PostgreSQL
# has, so both order a run's events by ``id``. The table is rebuilt: SQLite cannot add a key column.
_V3_SQLITE = _ROBOT_COLUMNS + """
CREATE TABLE events_numbered (
    id INTEGER PRIMARY KEY,
    run_id TEXT NOT NULL,
    time REAL NOT NULL,
    kind TEXT NOT NULL,
    message TEXT,
    data TEXT
);
INSERT INTO events_numbered (id, run_id, time, kind, message, data)
    SELECT rowid, run_id, time, kind, message, data FROM events ORDER BY rowid;
DROP TABLE events;
ALTER TABLE events_numbered RENAME TO events;
CREATE INDEX events_run ON events (run_id, id);
"""

_V3_POSTGRESQL = _ROBOT_COLUMNS + """
ALTER TABLE events ADD COLUMN id BIGSERIAL PRIMARY KEY;
CREATE INDEX events_run ON events (run_id, id);
"""

# PostgreSQL's change counter for ``StoreReader.version()`` (SQLite has ``PRAGMA data_version``): one
# row bumped by a statement trigger on every table a reader shows. The bump is part of the writing
# transaction, so the counter and the data it announces become visible together, at commit.
_V4_POSTGRESQL = """
CREATE TABLE store_changes (id INTEGER PRIMARY KEY CHECK (id = 1), counter BIGINT NOT NULL);
INSERT INTO store_changes (id, counter) VALUES (1, 0);
CREATE FUNCTION store_changed() RETURNS trigger LANGUAGE plpgsql AS $$
BEGIN
    UPDATE store_changes SET counter = counter + 1 WHERE id = 1;
    RETURN NULL;
END $$;
CREATE TRIGGER runs_changed AFTER INSERT OR UPDATE OR DELETE ON runs
    FOR EACH STATEMENT EXECUTE FUNCTION store_changed();
CREATE TRIGGER samples_changed AFTER INSERT OR UPDATE OR DELETE ON samples
    FOR EACH STATEMENT EXECUTE FUNCTION store_changed();
CREATE TRIGGER events_changed AFTER INSERT OR UPDATE OR DELETE ON events
    FOR EACH STATEMENT EXECUTE FUNCTION store_changed();
"""

# Issue 16: the pose stream of a move measured in motion. One row per move (per step), its samples as
# one compressed binary column (``procedures.kinds._stream`` encodes it: float64 columns t,
# pose, raw pose, quality), not one row per frame: a move is hundreds of samples and a run thousands
# of moves. Written in the same transaction as the step's sample, so it is committed with it.
def _v5(blob: str) -> str:
    return f"""
CREATE TABLE IF NOT EXISTS streams (
    run_id TEXT NOT NULL,
    step_index INTEGER NOT NULL,
    format TEXT NOT NULL,
    samples INTEGER NOT NULL,
    columns TEXT NOT NULL,
    meta TEXT,
    data {blob} NOT NULL,
    PRIMARY KEY (run_id, step_index)
);
"""


_V5_POSTGRESQL = _v5("BYTEA") + """
CREATE TRIGGER streams_changed AFTER INSERT OR UPDATE OR DELETE ON streams
    FOR EACH STATEMENT EXECUTE FUNCTION store_changed();
"""

# Issue 21: a session's test conditions (robot identity, payload, warm-up, operator) as a run-level record,
# one row per session, committed in the same transaction as the session's first sample. Before, the record
# rode in that sample's ``reference["session"]``; those samples are left as they were (nothing committed is
# rewritten) and ``RunStore.sessions`` reads them too.
def _v6(real: str) -> str:
    return f"""
CREATE TABLE IF NOT EXISTS session_conditions (
    run_id TEXT NOT NULL,
    started {real} NOT NULL,
    conditions TEXT NOT NULL,
    PRIMARY KEY (run_id, started)
);
"""


_V6_POSTGRESQL = _v6("DOUBLE PRECISION") + """
CREATE TRIGGER session_conditions_changed AFTER INSERT OR UPDATE OR DELETE ON session_conditions
    FOR EACH STATEMENT EXECUTE FUNCTION store_changed();
"""

MIGRATIONS: tuple[Migration, ...] = (
    Migration(1, "runs, samples and events (the store as first written)", _v1("REAL"), _v1("DOUBLE PRECISION")),
    Migration(2, "superseded samples and run leases", _v2("REAL"), _v2("DOUBLE PRECISION")),
    Migration(3, "the robot's identity on each run; events numbered", _V3_SQLITE, _V3_POSTGRESQL),
    Migration(4, "a change counter for readers (PostgreSQL; SQLite has data_version)", "", _V4_POSTGRESQL),
    Migration(5, "the pose stream of each move measured in motion (one compressed row per move)", _v5("BLOB"),
              _V5_POSTGRESQL),
    Migration(6, "the test conditions of each session of a run, a run-level record (no longer in a sample)",
              _v6("REAL"), _V6_POSTGRESQL),
)
LATEST = MIGRATIONS[-1].version

VERSION_TABLE = "CREATE TABLE IF NOT EXISTS schema_version (version INTEGER PRIMARY KEY, applied {real} NOT NULL, " \
                "description TEXT)"


def version_from_tables(tables: set[str]) -> int:
    """The version of a SQLite store written before ``schema_version`` existed, from its tables."""
    if "runs" not in tables:
        return 0
    return 2 if {"superseded_samples", "leases"} <= tables else 1
