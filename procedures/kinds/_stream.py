"""The pose stream of one move measured in motion, as a kind reads it and the run store keeps it.

``StreamRecord`` holds one move's poses on the robot controller's clock; ``to_stored``/``from_stored``
turn it into the store's row and back (one compressed binary column of float64 arrays,
``procedures.store.StoredStream``). The engine's step context acquires it (``StepContext.stream_motion``).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from procedures.store import StoredStream

FORMAT = "f8le-zlib/1"
COLUMNS = ("index", "t", "x", "y", "z", "a", "b", "c", "raw_x", "raw_y", "raw_z", "raw_a", "raw_b", "raw_c",
           "residual_rms", "timestamp_spread", "tracked")


@dataclass
class StreamRecord:
    """One move's pose stream (SI; times on the robot controller's clock).

    Attributes
    ----------
    index : (N,) trigger numbers of the samples (a gap is a dropped trigger; nothing is filled in)
    t : (N,) s, controller clock
    pose : (N, 6) the OPR pose in M after compensation [x, y, z m, a, b, c rad]
    raw : (N, 6) the OPR pose as solved
    residual_rms : (N,) m; timestamp_spread : (N,) s; tracked : (N,) crosses found by tracking
    meta : rate, exposure, triggers, dropped, drop reasons, the done signal, the clock fit, ...
    """

    index: np.ndarray
    t: np.ndarray
    pose: np.ndarray
    raw: np.ndarray
    residual_rms: np.ndarray
    timestamp_spread: np.ndarray
    tracked: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.t)

    @property
    def dropped(self) -> int:
        return int(self.meta.get("dropped", 0))

    def to_stored(self) -> StoredStream:
        """The store's row: the columns as one zlib-compressed little-endian float64 block."""
        table = np.column_stack([self.index, self.t, self.pose, self.raw, self.residual_rms,
                                 self.timestamp_spread, self.tracked]).astype("<f8") if len(self) else \
            np.empty((0, len(COLUMNS)), "<f8")
        return StoredStream(format=FORMAT, samples=len(self), columns=list(COLUMNS),
                            data=zlib.compress(table.tobytes(), 6), meta=self.meta)

    @classmethod
    def from_stored(cls, stored: StoredStream) -> StreamRecord:
        if stored.format != FORMAT:
            raise ValueError(f"pose stream format {stored.format!r} is not known (expected {FORMAT})")
        table = np.frombuffer(zlib.decompress(stored.data), dtype="<f8").reshape(stored.samples, len(stored.columns))
        col = {name: table[:, i] for i, name in enumerate(stored.columns)}
        return cls(index=col["index"].astype(np.int64), t=col["t"].copy(),
                   pose=np.column_stack([col[c] for c in ("x", "y", "z", "a", "b", "c")]),
                   raw=np.column_stack([col[f"raw_{c}"] for c in ("x", "y", "z", "a", "b", "c")]),
                   residual_rms=col["residual_rms"].copy(), timestamp_spread=col["timestamp_spread"].copy(),
                   tracked=col["tracked"].astype(np.int64), meta=dict(stored.meta or {}))

    def arrays(self) -> dict[str, list[Any]]:
        """JSON-able columns (``export --streams``)."""
        return {"index": self.index.tolist(), "t": self.t.tolist(), "pose": self.pose.tolist(),
                "raw": self.raw.tolist(), "residual_rms": self.residual_rms.tolist(),
                "timestamp_spread": self.timestamp_spread.tolist(), "tracked": self.tracked.tolist()}
