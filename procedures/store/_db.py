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

Trouble with the SQLite file is one typed line, never a raw ``sqlite3`` error: ``StoreFull`` (the disk or
the file is full: where, and how much is free), ``StoreLocked`` (another process holds the write lock
longer than the busy timeout: its pid when ``/proc/locks`` tells it), ``StoreDamaged`` (a malformed file:
how to recover it) and ``StoreReadOnly`` (a write to a store that could only be opened read-only). A runs
folder or store file this process cannot write is opened read-only (``mode=ro``, else ``immutable=1``
when not even the ``-shm`` file can be made), so the reading commands still work on it.

Test hooks (both honoured by every SQLite connection the store opens): ``$INSTRUMENT_SQLITE_MAX_PAGES``
sets ``PRAGMA max_page_count`` (the file cannot grow beyond that many pages: a full disk, as SQLite
reports it), ``$INSTRUMENT_STORE_TIMEOUT`` the busy timeout in seconds (default 30).
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
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
MAX_PAGES_ENV = "INSTRUMENT_SQLITE_MAX_PAGES"
TIMEOUT_ENV = "INSTRUMENT_STORE_TIMEOUT"


class StoreError(RunError):
    """The run store cannot be opened or used (unreachable server, newer schema ...): one line."""


class DuplicateStep(StoreError):
    """A step that is already stored as measured was written again (a resumed run must never do this)."""


class StoreTrouble(StoreError):
    """The store cannot take a write now but will once the cause is gone: a run pauses on it."""


class StoreFull(StoreTrouble):
    """The disk (or the file's page limit) is full."""


class StoreLocked(StoreTrouble):
    """Another process holds the store's write lock for longer than the busy timeout."""


class StoreDamaged(StoreError):
    """The store's file is malformed: recover it or move it aside."""


class StoreReadOnly(StoreError):
    """A write to a store that could only be opened read-only."""


def store_timeout(default: float = 30.0) -> float:
    """The busy timeout: ``$INSTRUMENT_STORE_TIMEOUT`` seconds if set (a test hook), else ``default``."""
    try:
        value = float(os.environ.get(TIMEOUT_ENV, ""))
    except ValueError:
        return default
    return value if value == value and 0 <= value < 1e6 else default


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

    def keep_reserve(self) -> None:
        """Hold a little room in reserve (SQLite) for ``release_reserve``; best effort, never raises."""
        ...

    def release_reserve(self) -> bool:
        """Give the reserve back (a full disk: room for a run to record its pause); whether there was one."""
        ...

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
    database.keep_reserve()
    return database


def migrate(database: Database) -> int:
    """Bring the store to the latest schema version, one migration per transaction; returns the version."""
    if getattr(database, "read_only", False):  # a read-only store is read as it is, if this software knows it
        return _read_only_version(database)
    if database.dialect == "sqlite":  # up to date: no write (a reader is not held up by another process's lock)
        with contextlib.suppress(StoreReadOnly):
            if _read_only_version(database) == LATEST:
                return LATEST
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


def _read_only_version(database: Database) -> int:
    tables = {r["name"] for r in database.rows("SELECT name FROM sqlite_master WHERE type = 'table'")}
    current = 0
    if "schema_version" in tables:
        row = database.rows("SELECT MAX(version) AS version FROM schema_version")
        current = int(row[0]["version"]) if row and row[0]["version"] is not None else 0
    current = current or version_from_tables(tables)
    if current > LATEST:
        raise StoreError(f"run store {database.location}: schema version {current} is newer than this software "
                         f"knows ({LATEST}); use a newer instrument")
    if current < LATEST:
        raise StoreReadOnly(f"store is read-only: {database.location} has schema version {current} and needs "
                            f"upgrading to {LATEST}, which cannot be written; open it once where it is writable")
    return current


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
_SQLITE_BUSY, _SQLITE_LOCKED, _SQLITE_READONLY, _SQLITE_IOERR, _SQLITE_CORRUPT, _SQLITE_FULL, _SQLITE_CANTOPEN, \
    _SQLITE_NOTADB = 5, 6, 8, 10, 11, 13, 14, 26
_WAL_WRITE_LOCK = 120  # the byte of the -shm file a WAL writer locks (SQLite's WALINDEX_LOCK_OFFSET)
RESERVE_BYTES = 128 * 1024
"""The room a SQLite store keeps in reserve (one row of ``store_reserve``, a table outside the versioned schema):
given back when the disk or the file is full, so that a run can still record its pause and reason."""
DISK_RESERVE_BYTES = 1024 * 1024
"""The same on the disk: the file ``runs.sqlite-reserve`` beside the store, deleted when the disk is full (room
for the WAL to take the pause), written again the next time the store is opened."""


def _free_mb(path: Path) -> str:
    try:
        return f"{shutil.disk_usage(path.parent).free / 1e6:.0f} MB free"
    except OSError:
        return "free space unknown"


def _inode(path: Path) -> int | None:
    try:
        return os.stat(path).st_ino
    except OSError:
        return None


def lock_holders(path: Path) -> list[int]:
    """The pids (other than this one) holding a write lock on the SQLite file ``path`` or on the WAL
    writer's byte of its ``-shm`` file, as ``/proc/locks`` lists them (empty where it cannot tell)."""
    db, shm = _inode(path), _inode(path.with_name(path.name + "-shm"))
    found: list[int] = []
    try:
        lines = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return found
    for line in lines:
        fields = line.split()
        if "->" in fields:  # a waiter: not the holder
            continue
        try:
            kind, pid, inode = fields[3], int(fields[4]), int(fields[5].rsplit(":", 1)[1])
            start, end = int(fields[6]), (None if fields[7] == "EOF" else int(fields[7]))
        except (IndexError, ValueError):
            continue
        if kind != "WRITE" or pid in (os.getpid(), -1) or pid in found:
            continue
        on_writer_byte = start <= _WAL_WRITE_LOCK and (end is None or end >= _WAL_WRITE_LOCK)
        if (db is not None and inode == db) or (shm is not None and inode == shm and on_writer_byte):
            found.append(pid)
    return found


def sqlite_trouble(exc: sqlite3.Error, path: Path, timeout: float) -> StoreError | None:
    """The one-line ``StoreError`` for what SQLite reported, or None when it is not store trouble."""
    message = str(exc)
    code = (getattr(exc, "sqlite_errorcode", None) or 0) & 0xFF
    if code == _SQLITE_FULL or "database or disk is full" in message:
        return StoreFull(f"store: disk full at {path} ({_free_mb(path)})")
    if code in (_SQLITE_BUSY, _SQLITE_LOCKED) or "database is locked" in message:
        pids = lock_holders(path)
        who = (f"pid {', '.join(map(str, pids))}" if pids
               else "its pid could not be found (not in /proc/locks: another host, or another connection of this one)")
        return StoreLocked(f"store locked by another process ({who}) for longer than {timeout:g} s: {path}")
    if code in (_SQLITE_CORRUPT, _SQLITE_NOTADB) or "malformed" in message or "not a database" in message:
        return StoreDamaged(
            f"store damaged: {path}: {message}; recover it with `sqlite3 {path} .recover | sqlite3 {path}.recovered` "
            f"and move the recovered file in its place (or move the damaged file aside: a new, empty store is then "
            f"made; the runs' own files under {path.parent} stay)")
    if code == _SQLITE_READONLY or "readonly database" in message:
        return StoreReadOnly(f"store is read-only: {path} (this command writes to it; the reading commands work)")
    if code == _SQLITE_CANTOPEN or "unable to open database file" in message:
        return StoreError(f"run store {path}: cannot open it ({message})")
    if code == _SQLITE_IOERR or "disk I/O error" in message:
        return StoreTrouble(f"store: disk I/O error at {path} ({_free_mb(path)}): {message}")
    return None


class SqliteDatabase:
    """The runs folder's ``runs.sqlite`` (WAL, ``synchronous=FULL``, autocommit); read-only (``read_only``)
    when the folder or the file cannot be written by this process."""

    dialect = "sqlite"

    def __init__(self, path: Path, *, timeout: float = 30.0) -> None:
        self.path = path
        self.location = str(path)
        self.timeout = timeout
        folder_writable = os.access(path.parent, os.W_OK)
        self.read_only = not folder_writable or (path.exists() and not os.access(path, os.W_OK))
        with self._translated():
            if self.read_only:
                if not path.is_file():
                    raise StoreReadOnly(f"store is read-only: {path.parent} cannot be written and holds no "
                                        f"{path.name}")
                self._db = self._open_read_only()
            else:
                self._db = sqlite3.connect(path, timeout=timeout, isolation_level=None, check_same_thread=False)
            self._db.row_factory = sqlite3.Row
            max_pages = os.environ.get(MAX_PAGES_ENV, "").strip()
            if max_pages.isdigit():
                self._db.execute(f"PRAGMA max_page_count = {int(max_pages)}")
            if not self.read_only:
                self._db.execute("PRAGMA journal_mode=WAL")
                self._db.execute("PRAGMA synchronous=FULL")  # a commit is on disk when it returns

    def _open_read_only(self) -> sqlite3.Connection:
        quoted = urllib.parse.quote(str(self.path.resolve()))
        last: sqlite3.Error | None = None
        for flags in ("mode=ro", "immutable=1"):  # immutable: not even the -shm file can be made
            try:
                connection = sqlite3.connect(f"file:{quoted}?{flags}", uri=True, timeout=self.timeout,
                                             isolation_level=None, check_same_thread=False)
            except sqlite3.Error as exc:
                last = exc
                continue
            try:
                connection.execute("SELECT COUNT(*) FROM sqlite_master").fetchone()
                return connection
            except sqlite3.DatabaseError as exc:
                connection.close()
                last = exc
                if (trouble := sqlite_trouble(exc, self.path, self.timeout)) is not None and \
                        isinstance(trouble, StoreDamaged):
                    raise trouble from None
        assert last is not None
        raise last

    @contextlib.contextmanager
    def _translated(self) -> Iterator[None]:
        try:
            yield
        except sqlite3.IntegrityError as exc:
            if "UNIQUE" in str(exc) and "samples" in str(exc):
                raise DuplicateStep(f"run store {self.location}: {exc}") from None
            raise
        except sqlite3.Error as exc:
            trouble = sqlite_trouble(exc, self.path, self.timeout)
            if trouble is None:
                raise
            raise trouble from None

    def execute(self, sql: str, params: Sequence[Any] = ()) -> int:
        with self._translated():
            return self._db.execute(sql, tuple(params)).rowcount

    def rows(self, sql: str, params: Sequence[Any] = ()) -> list[dict[str, Any]]:
        with self._translated():
            return [dict(row) for row in self._db.execute(sql, tuple(params)).fetchall()]

    @contextlib.contextmanager
    def transaction(self, lock: str | None = None) -> Iterator[None]:
        # BEGIN IMMEDIATE: this connection is the one writer until COMMIT (every lock name at once).
        with self._translated():
            self._db.execute("BEGIN IMMEDIATE")
        try:
            yield
            with self._translated():
                self._db.execute("COMMIT")
        except BaseException:
            if self._db.in_transaction:  # SQLite may have rolled back already (a full disk, for one)
                with contextlib.suppress(sqlite3.Error):
                    self._db.execute("ROLLBACK")
            raise

    @property
    def disk_reserve(self) -> Path:
        return self.path.with_name(self.path.name + "-reserve")

    def keep_reserve(self) -> None:
        if self.read_only:
            return
        if not self.disk_reserve.exists():
            try:
                with open(self.disk_reserve, "wb") as handle:
                    handle.write(bytes(DISK_RESERVE_BYTES))
                    handle.flush()
                    os.fsync(handle.fileno())
            except OSError:  # no room for it now: none (a short one would only mislead)
                with contextlib.suppress(OSError):
                    self.disk_reserve.unlink()
        with contextlib.suppress(StoreError):
            if self.rows("SELECT name FROM sqlite_master WHERE type = 'table' AND name = 'store_reserve'") and \
                    self.rows("SELECT id FROM store_reserve LIMIT 1"):
                return
            self._db.execute("PRAGMA busy_timeout = 0")  # another process's lock: no reserve now, and no wait
            try:
                self._fill_reserve()
            finally:
                self._db.execute(f"PRAGMA busy_timeout = {int(self.timeout * 1000)}")

    def _fill_reserve(self) -> None:
        with contextlib.suppress(StoreError):
            with self.transaction():
                self.execute("CREATE TABLE IF NOT EXISTS store_reserve (id INTEGER PRIMARY KEY, room BLOB NOT NULL)")
                self.execute("INSERT OR REPLACE INTO store_reserve (id, room) VALUES (1, zeroblob(?))",
                             (RESERVE_BYTES,))

    def release_reserve(self) -> bool:
        released = False
        try:  # the disk's first: the WAL needs it to take even the delete
            self.disk_reserve.unlink()
            released = True
        except OSError:
            pass
        try:
            return self.execute("DELETE FROM store_reserve") > 0 or released
        except StoreError:
            return released

    def version(self) -> int:
        """Changes exactly when another connection commits (``PRAGMA data_version``)."""
        with self._translated():
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

    def keep_reserve(self) -> None:
        pass  # the server keeps its own room

    def release_reserve(self) -> bool:
        return False

    def version(self) -> int:
        """The ``store_changes`` counter: bumped by every committed change of runs, samples or events."""
        return int(self.rows("SELECT counter FROM store_changes WHERE id = 1")[0]["counter"])

    def close(self) -> None:
        with self._lock:
            self._conn.close()


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]
