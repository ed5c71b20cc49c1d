"""Writes the UR twin's dense truth: one record per move (format: ``sim_devices.trajectory``).

``TrajectoryRecorder`` lives in the controller's cycle thread: ``open`` when a move starts,
``append`` every cycle's truth samples (buffered; written every ``FLUSH_ROWS`` rows so a reader in
another process sees the truth a few tens of milliseconds behind), ``close`` once the residual
vibration has died out or the next move starts. Without a directory it keeps the records in memory
only (the last ``KEEP`` of them, for tests and the twin's control API).
"""

from __future__ import annotations

import json
import os
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from sim_devices.trajectory import HEADER_BYTES, WIDTH, encode_header

FLUSH_ROWS = 32
KEEP = 16


class TrajectoryRecorder:
    """See the module docstring.

    Parameters
    ----------
    directory : path or None
        Where the ``move-NNNNNN.traj`` files go (created); None keeps records in memory only.
    truth : TruthLog or None
        Gets one ``trajectory`` entry per closed record.
    meta : dict
        Header fields every record shares (time scale, control period).
    """

    def __init__(self, directory: str | Path | None, truth: Any, meta: dict[str, Any]) -> None:
        self.directory = Path(directory) if directory else None
        if self.directory is not None:
            self.directory.mkdir(parents=True, exist_ok=True)
        self.truth = truth
        self.meta = dict(meta)
        self.moves = 0
        self.current: dict[str, Any] | None = None  # the open record's header and summary so far
        self._rows: list[np.ndarray] = []  # every row of the open record (kept for the in-memory copy)
        self._unwritten: list[np.ndarray] = []  # rows not yet written to the file
        self._fd: int | None = None
        self._path: Path | None = None
        self.closed: deque[dict[str, Any]] = deque(maxlen=KEEP)  # summary + rows of the last records

    @property
    def is_open(self) -> bool:
        return self.current is not None

    def write_clock(self, description: dict[str, Any]) -> None:
        """``clock.json``: how controller time relates to this machine's monotonic clock."""
        if self.directory is None:
            return
        tmp = self.directory / ".clock.json.tmp"
        tmp.write_text(json.dumps(description))
        os.replace(tmp, self.directory / "clock.json")

    def open(self, meta: dict[str, Any]) -> int:
        """Start the record of a new move (closing any open one); returns its move number."""
        if self.current is not None:
            self.close()
        self.moves += 1
        self.current = {**self.meta, **meta, "move": self.moves}
        self._rows = []
        self._unwritten = []
        if self.directory is not None:
            self._path = self.directory / f"move-{self.moves:06d}.traj"
            self._fd = os.open(self._path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            os.write(self._fd, encode_header(self.current))
            assert os.lseek(self._fd, 0, os.SEEK_CUR) == HEADER_BYTES
        return self.moves

    def append(self, rows: np.ndarray) -> None:
        """Samples (n, WIDTH) of the open record."""
        if self.current is None:
            return
        assert rows.shape[1] == WIDTH
        rows = np.ascontiguousarray(rows, dtype="<f8")
        self._rows.append(rows)
        self._unwritten.append(rows)
        if sum(len(r) for r in self._unwritten) >= FLUSH_ROWS:
            self._flush()

    def note(self, **summary: Any) -> None:
        """Add to the open record's summary (written when it closes)."""
        if self.current is not None:
            self.current.update(summary)

    def _flush(self) -> None:
        if self._fd is not None and self._unwritten:
            os.write(self._fd, np.concatenate(self._unwritten).tobytes())  # whole rows, appended in one write
        self._unwritten = []

    def close(self) -> dict[str, Any] | None:
        """End the open record: the rows, the summary file and the truth-log entry. Returns the summary."""
        if self.current is None:
            return None
        self._flush()
        rows = np.concatenate(self._rows) if self._rows else np.empty((0, WIDTH))
        summary = {**self.current, "rows": int(len(rows))}
        if len(rows):
            summary["t_end"] = float(rows[-1, 0])
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
            assert self._path is not None
            summary["file"] = self._path.name
            tmp = self._path.with_name(f".{self._path.stem}.json.tmp")
            tmp.write_text(json.dumps(summary))
            os.replace(tmp, self._path.with_suffix(".json"))
        if self.truth is not None:
            self.truth.record("trajectory", **summary)
        self.closed.append({**summary, "data": rows})
        self.current = None
        self._rows = []
        return summary

    def record(self, move: int | None = None) -> dict[str, Any] | None:
        """A record kept in memory (the last closed one by default, or the open one if it is ``move``)."""
        if self.current is not None and move == self.current["move"]:
            rows = np.concatenate(self._rows) if self._rows else np.empty((0, WIDTH))
            return {**self.current, "data": rows, "open": True}
        for entry in reversed(self.closed):
            if move is None or entry["move"] == move:
                return entry
        return None
