"""Ground truth of a simulated cell: the world's JSON-lines log, matched to samples by time."""

from __future__ import annotations

import bisect
import json
from pathlib import Path
from typing import Any


class TruthLog:
    """The settled poses of the simulated world, in time order."""

    def __init__(self, entries: list[dict[str, Any]]) -> None:
        self.entries = sorted((e for e in entries if e.get("event") == "pose" and "time" in e), key=lambda e: e["time"])
        self.times = [e["time"] for e in self.entries]

    @classmethod
    def read(cls, *paths: str | Path) -> TruthLog:
        """The logs at ``paths`` merged by time (a resumed run may have been measured on several cells)."""
        entries = []
        for path in paths:
            with open(path, encoding="utf-8", errors="replace") as handle:
                for line in handle:
                    line = line.strip()
                    if not line:
                        continue
                    try:
                        entries.append(json.loads(line))
                    except json.JSONDecodeError:
                        continue  # a line cut short by a crash
        return cls(entries)

    def at(self, when: float) -> dict[str, Any] | None:
        """The last settled pose at or before ``when`` (host seconds)."""
        index = bisect.bisect_right(self.times, when) - 1
        return self.entries[index] if index >= 0 else None
