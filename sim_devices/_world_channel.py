"""The world's one channel between the cell's processes: a small memory-mapped state file.

Every twin of a cell runs in its own process; they share the physical truth (true flange pose,
OPR mount, table angle, the settled flag) through this file, ``<cell>/world/state``, mapped into
each of them. It holds, little-endian:

=========  =====================================================================================
header     magic ``OPRWORLD``, layout number (``LAYOUT``), number of subscriber slots
state      a seqlock'd record: counter (odd while being written), seq, seq of the last settled
           state, time, settled, mount code, flange pose (16 doubles, row-major ``T_B_F``), angle
settled    a seqlock'd copy of the latest *settled* state record (same layout as ``state``), so a
           process that wakes after a settled state was overtaken by moving ones still gets that
           settled state's own data (not a pose the robot was merely passing through)
hint       a seqlock'd record of what a twin expects to settle at next (an *announcement*): id,
           flange pose and/or table angle; lets the camera twin render ahead of time
slots      one per process that subscribes: pid (0: free) and the last seq it has seen (its ack)
=========  =====================================================================================

Writers (any process) serialise on an ``flock`` of the file plus a thread lock; readers never
block: they copy the record and retry while the counter is odd or changed (a seqlock), so the
1 kHz interferometer clock and the 500 Hz robot cycle never wait on each other. A process with
subscribers owns a slot and a wake-up FIFO (``wake-<slot>``); publishers write one byte into every
other slot's FIFO (non-blocking: a full FIFO already holds a wake-up) and, for a settled state,
wait until every slot has acknowledged it, so that "done" is only reported once every twin (the
camera renderer) has seen the pose.
"""

from __future__ import annotations

import errno
import fcntl
import mmap
import os
import struct
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MAGIC = b"OPRWORLD"
LAYOUT = 2  # 2: the last settled record has a slot of its own
SLOTS = 8
MOUNTS = ("robot", "table:x", "table:y", "table:z")

_HEADER = struct.Struct("<8sII")  # magic, layout, slots
_STATE = struct.Struct("<QQdBB6x16dd")  # seq, last settled seq, time, settled, mount, flange, angle
_HINT = struct.Struct("<QBB6x16dd")  # id, has_flange, has_angle, flange, angle
_COUNTER = struct.Struct("<Q")
_SLOT = struct.Struct("<QQ")  # pid, ack seq

_STATE_OFFSET = _HEADER.size  # counter, then the record
_SETTLED_OFFSET = _STATE_OFFSET + _COUNTER.size + _STATE.size  # counter, then the last settled record
_HINT_OFFSET = _SETTLED_OFFSET + _COUNTER.size + _STATE.size
_SLOTS_OFFSET = _HINT_OFFSET + _COUNTER.size + _HINT.size
SIZE = _SLOTS_OFFSET + SLOTS * _SLOT.size


class ChannelError(RuntimeError):
    """The state file is missing, of another layout, or full (no free subscriber slot)."""


@dataclass(frozen=True)
class StateRecord:
    """One consistent copy of the shared state."""

    seq: int
    time: float
    settled: bool
    mount: str
    flange: np.ndarray  # 4×4
    table_angle: float
    last_settled: int  # seq of the latest settled state (this one if settled)


@dataclass(frozen=True)
class Hint:
    """An announced state to come: ``flange`` and/or ``table_angle`` (None: unchanged)."""

    id: int
    flange: np.ndarray | None
    table_angle: float | None


class WorldChannel:
    """One process's view of the shared state file (see the module docstring).

    Use ``WorldChannel.create(directory, ...)`` once (the cell supervisor) and
    ``WorldChannel.attach(directory)`` in every twin process; ``close()`` when done.
    """

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        self.path = self.directory / "state"
        try:
            self._fd = os.open(self.path, os.O_RDWR)
        except FileNotFoundError:
            raise ChannelError(f"world channel: no state file {self.path}") from None
        try:
            self._map = mmap.mmap(self._fd, SIZE)
        except ValueError:
            os.close(self._fd)
            raise ChannelError(f"world channel: {self.path} is too short for layout {LAYOUT}") from None
        magic, layout, slots = _HEADER.unpack_from(self._map, 0)
        if magic != MAGIC or layout != LAYOUT or slots != SLOTS:
            self.close()
            raise ChannelError(f"world channel: {self.path} has layout {magic!r}/{layout}/{slots}, "
                               f"expected {MAGIC!r}/{LAYOUT}/{SLOTS}")
        self._thread_lock = threading.RLock()
        self._wake_fds: dict[int, int] = {}
        self.closed = False

    # ----------------------------------------------------------------------------- set-up
    @classmethod
    def create(cls, directory: str | Path, *, flange: np.ndarray, mount: str = "robot", table_angle: float = 0.0,
               settled: bool = True, time_now: float = 0.0) -> WorldChannel:
        """Write a fresh state file (seq 0) in ``directory`` and map it."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        for stale in directory.glob("wake-*"):
            stale.unlink(missing_ok=True)
        buffer = bytearray(SIZE)
        _HEADER.pack_into(buffer, 0, MAGIC, LAYOUT, SLOTS)
        for offset in (_STATE_OFFSET, _SETTLED_OFFSET):  # seq 0 counts as settled, whatever its flag
            _STATE.pack_into(buffer, offset + _COUNTER.size, 0, 0, time_now, settled, MOUNTS.index(mount),
                             *np.asarray(flange, dtype=float).reshape(16), float(table_angle))
        tmp = directory / ".state.tmp"
        tmp.write_bytes(bytes(buffer))
        os.replace(tmp, directory / "state")
        return cls(directory)

    @classmethod
    def attach(cls, directory: str | Path) -> WorldChannel:
        return cls(directory)

    def close(self) -> None:
        """Unmap the file and close the wake-up FIFOs this process opened."""
        if getattr(self, "closed", True):
            return
        self.closed = True
        for fd in self._wake_fds.values():
            _close_quietly(fd)
        self._wake_fds.clear()
        self._map.close()
        os.close(self._fd)

    # ----------------------------------------------------------------------------- state
    def read(self) -> StateRecord:
        """The current state, consistent (never half written)."""
        return _unpack_state(self._read_seqlocked(_STATE_OFFSET, _STATE.size))

    def read_settled(self) -> StateRecord:
        """The latest settled state, with its own data (its seq is at least the ``last_settled`` of any
        state record read before: a writer puts it here before it publishes the state record)."""
        return _unpack_state(self._read_seqlocked(_SETTLED_OFFSET, _STATE.size))

    def seq(self) -> int:
        return int(self.read().seq)

    def write(self, *, flange: np.ndarray | None = None, mount: str | None = None, table_angle: float | None = None,
              settled: bool | None = None, time_now: float) -> StateRecord:
        """Change some fields, advance seq by one; returns the new state. Serialised across processes."""
        with self.locked():
            current = self.read()
            now_settled = current.settled if settled is None else bool(settled)
            record = StateRecord(
                current.seq + 1, float(time_now), now_settled, current.mount if mount is None else mount,
                current.flange if flange is None else np.asarray(flange, dtype=float).reshape(4, 4).copy(),
                current.table_angle if table_angle is None else float(table_angle),
                current.seq + 1 if now_settled else current.last_settled,
            )
            payload = _STATE.pack(record.seq, record.last_settled, record.time, record.settled,
                                  MOUNTS.index(record.mount), *record.flange.reshape(16), record.table_angle)
            if record.settled:
                # First the settled slot, then the state: whoever reads a state whose last_settled is
                # this seq finds this record (or a newer settled one) in the slot.
                self._write_seqlocked(_SETTLED_OFFSET, payload)
            self._write_seqlocked(_STATE_OFFSET, payload)
            return record

    # ----------------------------------------------------------------------------- hints
    def read_hint(self) -> Hint:
        raw = self._read_seqlocked(_HINT_OFFSET, _HINT.size)
        hint_id, has_flange, has_angle, *values = _HINT.unpack(raw)
        return Hint(hint_id, np.array(values[:16]).reshape(4, 4) if has_flange else None,
                    values[16] if has_angle else None)

    def write_hint(self, *, flange: np.ndarray | None = None, table_angle: float | None = None) -> int:
        """Announce a state to come; returns the hint's id."""
        with self.locked():
            hint_id = self.read_hint().id + 1
            matrix = np.zeros(16) if flange is None else np.asarray(flange, dtype=float).reshape(16)
            payload = _HINT.pack(hint_id, flange is not None, table_angle is not None, *matrix,
                                 0.0 if table_angle is None else float(table_angle))
            self._write_seqlocked(_HINT_OFFSET, payload)
            return hint_id

    # ----------------------------------------------------------------------------- slots
    def claim_slot(self) -> int:
        """A subscriber slot for this process (its FIFO created); ChannelError when all are taken."""
        with self.locked():
            for index in range(SLOTS):
                pid, _ = self._slot(index)
                if pid == 0 or not _alive(pid):
                    fifo = self.wake_path(index)
                    fifo.unlink(missing_ok=True)
                    os.mkfifo(fifo, 0o600)
                    self._set_slot(index, os.getpid(), self.seq())
                    return index
        raise ChannelError(f"world channel: all {SLOTS} subscriber slots are taken")

    def release_slot(self, index: int) -> None:
        with self.locked():
            self._set_slot(index, 0, 0)
        self.wake_path(index).unlink(missing_ok=True)

    def release_slots_of(self, pid: int) -> list[int]:
        """Free every slot held by ``pid`` (a twin that died); returns their indices."""
        freed = []
        with self.locked():
            for index in range(SLOTS):
                if self._slot(index)[0] == pid:
                    self._set_slot(index, 0, 0)
                    freed.append(index)
        for index in freed:
            self.wake_path(index).unlink(missing_ok=True)
        return freed

    def ack(self, index: int, seq: int) -> None:
        """The subscriber of slot ``index`` has seen every state up to ``seq``."""
        pid, _ = self._slot(index)
        if pid == os.getpid():
            _SLOT.pack_into(self._map, _SLOTS_OFFSET + index * _SLOT.size, pid, seq)

    def subscribers(self) -> list[tuple[int, int, int]]:
        """``(slot, pid, ack)`` of every taken slot."""
        return [(i, pid, ack) for i in range(SLOTS) for pid, ack in [self._slot(i)] if pid]

    def wake_path(self, index: int) -> Path:
        return self.directory / f"wake-{index}"

    def wake_others(self) -> None:
        """One byte into the FIFO of every other process's slot (never blocks)."""
        me = os.getpid()
        for index, pid, _ in self.subscribers():
            if pid == me:
                continue
            fd = self._wake_fds.get(index)
            try:
                if fd is None:
                    fd = os.open(self.wake_path(index), os.O_WRONLY | os.O_NONBLOCK)
                    self._wake_fds[index] = fd
                os.write(fd, b"\x01")
            except BlockingIOError:
                pass  # the FIFO is full: the subscriber has a wake-up pending anyway
            except OSError as exc:  # no reader (ENXIO), reader gone (EPIPE), slot freed (ENOENT)
                if exc.errno not in (errno.ENXIO, errno.EPIPE, errno.ENOENT):
                    raise
                stale = self._wake_fds.pop(index, None)
                if stale is not None:
                    _close_quietly(stale)

    def wait_for_acks(self, seq: int, timeout: float) -> list[int]:
        """Block until every other process's slot has acknowledged ``seq``; returns the pids that did
        not within ``timeout`` s (a freed slot, or a dead process, counts as acknowledged)."""
        me = os.getpid()
        deadline = time.monotonic() + timeout
        pause = 0.0002
        while True:
            late = [pid for _, pid, ack in self.subscribers() if pid != me and ack < seq and _alive(pid)]
            if not late or time.monotonic() >= deadline:
                return late
            time.sleep(pause)
            pause = min(pause * 1.5, 0.002)

    # ----------------------------------------------------------------------------- internals
    @contextmanager
    def locked(self) -> Iterator[None]:
        """The writer lock: this process's threads, then the other processes (``flock``)."""
        with self._thread_lock:
            fcntl.flock(self._fd, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(self._fd, fcntl.LOCK_UN)

    def _read_seqlocked(self, offset: int, size: int) -> bytes:
        start = offset + _COUNTER.size
        while True:
            before = _COUNTER.unpack_from(self._map, offset)[0]
            if before & 1:
                time.sleep(0)  # a writer is half way through; let it finish
                continue
            raw = self._map[start:start + size]
            if _COUNTER.unpack_from(self._map, offset)[0] == before:
                return raw

    def _write_seqlocked(self, offset: int, payload: bytes) -> None:
        counter = _COUNTER.unpack_from(self._map, offset)[0]
        _COUNTER.pack_into(self._map, offset, counter + 1)  # odd: readers retry
        start = offset + _COUNTER.size
        self._map[start:start + len(payload)] = payload
        _COUNTER.pack_into(self._map, offset, counter + 2)

    def _slot(self, index: int) -> tuple[int, int]:
        pid, ack = _SLOT.unpack_from(self._map, _SLOTS_OFFSET + index * _SLOT.size)
        return int(pid), int(ack)

    def _set_slot(self, index: int, pid: int, ack: int) -> None:
        _SLOT.pack_into(self._map, _SLOTS_OFFSET + index * _SLOT.size, pid, ack)


def _unpack_state(raw: bytes) -> StateRecord:
    seq, last_settled, when, settled, mount, *values = _STATE.unpack(raw)
    return StateRecord(seq, when, bool(settled), MOUNTS[mount], np.array(values[:16]).reshape(4, 4), values[16],
                       last_settled)


class WakeUps:
    """The read end of one slot's FIFO: ``wait(timeout)`` returns when woken (or on timeout)."""

    def __init__(self, path: Path) -> None:
        # O_RDWR keeps the FIFO open for writing too, so it never reports end-of-file.
        self._fd = os.open(path, os.O_RDWR | os.O_NONBLOCK)

    def wait(self, timeout: float) -> None:
        import select

        ready, _, _ = select.select([self._fd], [], [], timeout)
        if ready:
            try:
                while os.read(self._fd, 4096):
                    pass
            except BlockingIOError:
                pass

    def close(self) -> None:
        _close_quietly(self._fd)


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, dead but not yet reaped by its parent, does not)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f"/proc/{pid}/stat", "rb") as handle:
            return handle.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    except (OSError, IndexError):
        return True


def _close_quietly(fd: int) -> None:
    try:
        os.close(fd)
    except OSError:
        pass
