"""The run store's two databases behind one small interface: SQLite (embedded, the default) and PostgreSQL.

``RunStore`` writes its SQL once, with ``?`` placeholders; a ``Database`` runs it on its backend and
hands rows back as dicts. What differs between the two is here and only here:

- **SQLite**: one file ``<runs>/runs.sqlite`` in WAL mode with ``synchronous=FULL`` (a commit is on
  disk when it returns); a transaction that must see and change atomically starts with ``BEGIN
  IMMEDIATE`` (the one writer from there to its commit); ``version()`` is ``PRAGMA data_version``.
- **PostgreSQL** (psycopg 3): a server many cells share, given as ``postgresql://…`` (``--store`` or
  ``$INSTRUMENT_STORE``); autocommit, a transaction where several statements must hold together; the
  lease is taken under a transaction-scoped advisory lock on the run id and a state change holds the
  lease row ``FOR SHARE`` (see ``RunStore``); ``version()`` reads the ``store_changes`` counter that
  statement triggers bump in the writing transaction.

Per-run files (frames, calibration records, reports) are never in the database: they stay in the runs
folder on the local or a shared filesystem on both backends.
"""

from __future__ import annotations

import contextlib
import os
import re
import sqlite3
import threading
import time
import urllib.parse
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, Protocol

from procedures.station import RunError
from procedures.store._schema import LATEST, MIGRATIONS, VERSION_TABLE, version_from_tables

STORE_ENV = "INSTRUMENT_STORE"
SQLITE_FILE = "runs.sqlite"


class StoreError(RunError):
    """The run store cannot be opened or used (unreachable server, newer schema ...): one line."""


class DuplicateStep(StoreError):
    """A step that is already stored as measured was written again (a resumed run must never do this)."""


class Database(Protocol):
    dialect: str
    location: str

    def execute(self, sql: str, params: Sequence[Any] = ()) -> int:
        """Run one statement; returns the number of rows it changed."""
        ...

    def rows(self, sql: str, params: Sequence[Any] = ()) -> list[dict[str, Any]]: ...

    def transaction(self, lock: str | None = None) -> contextlib.AbstractContextManager[None]:
        """One transaction; ``lock``: a name serialising the transactions that give the same one."""
        ...

    def version(self) -> int: ...

    def close(self) -> None: ...


def store_location(url: str | None) -> str | None:
    """The PostgreSQL URL to use (``url``, else ``$INSTRUMENT_STORE``), or None for the runs folder's SQLite file.

    Raises
    ------
    StoreError
        The value is neither empty nor a ``postgresql://`` URL.
    """
    value = (url if url is not None else os.environ.get(STORE_ENV, "")).strip()
    if not value or value == "sqlite":
        return None
    if not re.match(r"^postgres(ql)?://", value):
        source = "--store" if url is not None else f"${STORE_ENV}"
        raise StoreError(f"{source}: expected a postgresql://USER@HOST/DATABASE URL (or nothing, for the runs "
                         f"folder's SQLite file), got {shown_url(value)!r}")
    return value


def shown_url(url: str) -> str:
    """``url`` with its password replaced by ``***`` (messages and listings never show it)."""
    try:
        parts = urllib.parse.urlsplit(url)
    except ValueError:
        return "<unparsable URL>"
    if parts.password is None:
        return url
    netloc = parts.netloc.replace(f":{parts.password}@", ":***@", 1)
    return urllib.parse.urlunsplit(parts._replace(netloc=netloc))


def connect(runs_dir: Path, url: str | None, *, timeout: float = 30.0) -> Database:
    """The store's database: PostgreSQL at ``url``, else SQLite in ``runs_dir``; migrated to the latest schema."""
    database: Database = PostgresDatabase(url, timeout=timeout) if url else SqliteDatabase(
        runs_dir / SQLITE_FILE, timeout=timeout)
    try:
        migrate(database)
    except BaseException:
        database.close()
        raise
    return database


def migrate(database: Database) -> int:
    """Bring the store to the latest schema version, one migration per transaction; returns the version."""
    real = "REAL" if database.dialect == "sqlite" else "DOUBLE PRECISION"
    with database.transaction(lock="schema"):
        database.execute(VERSION_TABLE.format(real=real))
        current = _current_version(database)
    if current > LATEST:
        raise StoreError(f"run store {database.location}: schema version {current} is newer than this software "
                         f"knows ({LATEST}); use a newer instrument")
    for migration in MIGRATIONS:
        if migration.version <= current:
            continue
        with database.transaction(lock="schema"):
            if _current_version(database) >= migration.version:  # another process got there first
                continue
            for statement in _statements(migration.script(database.dialect), database.dialect):
                database.execute(statement)
            database.execute("INSERT INTO schema_version (version, applied, description) VALUES (?, ?, ?)",
                             (migration.version, time.time(), migration.description))
    return max(current, LATEST)


def _current_version(database: Database) -> int:
    row = database.rows("SELECT MAX(version) AS version FROM schema_version")
    if row and row[0]["version"] is not None:
        return int(row[0]["version"])
    if database.dialect != "sqlite":
        return 0
    tables = {r["name"] for r in database.rows("SELECT name FROM sqlite_master WHERE type = 'table'")}
    found = version_from_tables(tables)
    if found:  # a store from before versioning: record what it is, so the next migration starts there
        database.execute("INSERT INTO schema_version (version, applied, description) VALUES (?, ?, ?)",
                         (found, time.time(), "found in a store written before schema versions"))
    return found


def _statements(script: str, dialect: str) -> list[str]:
    if dialect != "sqlite":
        return [script] if script.strip() else []  # PostgreSQL takes a whole script (function bodies hold ';')
    return [part.strip() for part in script.split(";\n") if part.strip()]


# ------------------------------------------------------------------------------------------ SQLite
class SqliteDatabase:
    """The runs folder's ``runs.sqlite`` (WAL, ``synchronous=FULL``, autocommit)."""

    dialect = "sqlite"

    def __init__(self, path: Path, *, timeout: float = 30.0) -> None:
        self.path = path
        self.location = str(path)
        self._db = sqlite3.connect(path, timeout=timeout, isolation_level=None, check_same_thread=False)
        self._db.row_factory = sqlite3.Row
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")  # a commit is on disk when it returns

    def execute(self, sql: str, params: Sequence[Any] = ()) -> int:
        try:
            return self._db.execute(sql, tuple(params)).rowcount
        except sqlite3.IntegrityError as exc:
            if "UNIQUE" in str(exc) and "samples" in str(exc):
                raise DuplicateStep(f"run store {self.location}: {exc}") from None
            raise

    def rows(self, sql: str, params: Sequence[Any] = ()) -> list[dict[str, Any]]:
        return [dict(row) for row in self._db.execute(sql, tuple(params)).fetchall()]

    @contextlib.contextmanager
    def transaction(self, lock: str | None = None) -> Iterator[None]:
        # BEGIN IMMEDIATE: this connection is the one writer until COMMIT (every lock name at once).
        self._db.execute("BEGIN IMMEDIATE")
        try:
            yield
            self._db.execute("COMMIT")
        except BaseException:
            self._db.execute("ROLLBACK")
            raise

    def version(self) -> int:
        """Changes exactly when another connection commits (``PRAGMA data_version``)."""
        return int(self._db.execute("PRAGMA data_version").fetchone()[0])

    def close(self) -> None:
        self._db.close()


# -------------------------------------------------------------------------------------- PostgreSQL
class PostgresDatabase:
    """A PostgreSQL database shared by many cells (psycopg 3, autocommit)."""

    dialect = "postgresql"

    def __init__(self, url: str, *, timeout: float = 30.0) -> None:
        try:
            import psycopg
            from psycopg.rows import dict_row
        except ImportError:  # pragma: no cover - a dependency of the project
            raise StoreError("a postgresql:// store needs psycopg 3 (pip install 'psycopg[binary]')") from None
        self._psycopg = psycopg
        self.location = shown_url(url)
        self._lock = threading.RLock()  # one connection: statements of two threads must not interleave
        self._in_transaction = False
        try:
            self._conn = psycopg.connect(url, autocommit=True, row_factory=dict_row,
                                         connect_timeout=max(1, int(timeout)))
        except psycopg.Error as exc:
            raise StoreError(f"run store {self.location}: cannot connect: {_first_line(exc)}") from None
        # Every wait has a bound: a statement blocked on a lock gives up with an error, not a hang.
        self._conn.execute(f"SET lock_timeout = '{int(timeout * 1000)}ms'")

    @staticmethod
    def _sql(sql: str) -> str:
        return sql.replace("%", "%%").replace("?", "%s")

    def _run(self, sql: str, params: Sequence[Any]):
        psycopg = self._psycopg
        try:
            return self._conn.execute(self._sql(sql), tuple(params) if params else None)
        except psycopg.errors.UniqueViolation as exc:
            if "samples" in str(exc):
                raise DuplicateStep(f"run store {self.location}: {_first_line(exc)}") from None
            raise
        except psycopg.OperationalError as exc:
            raise StoreError(f"run store {self.location}: {_first_line(exc)}") from None

    def execute(self, sql: str, params: Sequence[Any] = ()) -> int:
        with self._lock:
            return self._run(sql, params).rowcount

    def rows(self, sql: str, params: Sequence[Any] = ()) -> list[dict[str, Any]]:
        with self._lock:
            return list(self._run(sql, params).fetchall())

    @contextlib.contextmanager
    def transaction(self, lock: str | None = None) -> Iterator[None]:
        with self._lock:
            try:
                with self._conn.transaction():
                    if lock is not None:  # held to the end of this transaction, released at commit or rollback
                        self._run("SELECT pg_advisory_xact_lock(hashtextextended(?, 0))", (f"instrument:{lock}",))
                    yield
            except self._psycopg.OperationalError as exc:
                raise StoreError(f"run store {self.location}: {_first_line(exc)}") from None

    def version(self) -> int:
        """The ``store_changes`` counter: bumped by every committed change of runs, samples or events."""
        return int(self.rows("SELECT counter FROM store_changes WHERE id = 1")[0]["counter"])

    def close(self) -> None:
        with self._lock:
            self._conn.close()


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]
