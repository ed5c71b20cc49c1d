"""The dense ground truth of the robot's motion: one binary trajectory file per move.

The UR twin samples the TRUE tool motion (``sim_devices.arm`` structural modes) at ``truth_rate``
(default 1 kHz of simulated time) from the moment a move starts until its residual vibration has
died out (or the next move starts), and writes it to ``<cell>/trajectories/move-NNNNNN.traj``:

- a header of ``HEADER_BYTES`` bytes: one JSON object (``format``, ``columns``, ``move``, ``kind``,
  ``time_scale``, ``control_period``, ``tcp_offset``, ``t_start``), padded with spaces;
- then rows of float64 (little endian), one per sample, ``COLUMNS``: the controller time (s, the
  RTDE ``timestamp`` clock), the TRUE flange pose (position m, unit quaternion w, x, y, z), the
  COMMANDED TCP pose and the ENCODER TCP pose (what ``actual_TCP_pose`` reports), both in the base
  frame.

Rows are appended while the move runs (a reader trims a partly written last row). When the record
closes, ``move-NNNNNN.json`` is written beside it (the summary: ``profile_end``, ``servo_settled``,
``done_timestamp`` — the controller time of the first RTDE package that reported the move done —,
``t_end``, the commanded target and the attained pose) and the truth log gets a ``trajectory``
entry with the same summary. Between records the robot is at rest at the last record's final pose.

``TrajectoryLog(directory)`` reads them all: ``flange_at(times)`` interpolates the true flange
pose at any controller times (position linearly, orientation by normalised quaternion
interpolation), ``known_until()`` says up to when the truth is written, and ``true_poses_in_m``
turns flange poses into the OPR's or the tool's pose in M with the world's true constants.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

FORMAT = "opr-ur-trajectory/1"
HEADER_BYTES = 4096
COLUMNS = ("t",
           "flange_x", "flange_y", "flange_z", "flange_qw", "flange_qx", "flange_qy", "flange_qz",
           "commanded_x", "commanded_y", "commanded_z", "commanded_qw", "commanded_qx", "commanded_qy", "commanded_qz",
           "encoder_x", "encoder_y", "encoder_z", "encoder_qw", "encoder_qx", "encoder_qy", "encoder_qz")
WIDTH = len(COLUMNS)


def encode_header(meta: dict[str, Any]) -> bytes:
    """The fixed-size header of a trajectory file."""
    text = json.dumps({"format": FORMAT, "columns": list(COLUMNS), "header_bytes": HEADER_BYTES, **meta})
    if len(text) >= HEADER_BYTES:
        raise ValueError("trajectory header too long")
    return (text + " " * (HEADER_BYTES - 1 - len(text)) + "\n").encode()


def quaternions_to_matrices(q: np.ndarray) -> np.ndarray:
    """(n, 4) quaternions (w, x, y, z; normalised here) → (n, 3, 3) rotations."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r = np.empty((len(q), 3, 3))
    r[:, 0, 0] = 1 - 2 * (y * y + z * z)
    r[:, 0, 1] = 2 * (x * y - w * z)
    r[:, 0, 2] = 2 * (x * z + w * y)
    r[:, 1, 0] = 2 * (x * y + w * z)
    r[:, 1, 1] = 1 - 2 * (x * x + z * z)
    r[:, 1, 2] = 2 * (y * z - w * x)
    r[:, 2, 0] = 2 * (x * z - w * y)
    r[:, 2, 1] = 2 * (y * z + w * x)
    r[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def _transforms(position: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
    out = np.zeros((len(position), 4, 4))
    out[:, :3, :3] = quaternions_to_matrices(quaternion)
    out[:, :3, 3] = position
    out[:, 3, 3] = 1.0
    return out


@dataclass(frozen=True)
class Trajectory:
    """One move's record.

    Attributes
    ----------
    path : Path or None
    meta : dict
        The header (and, once closed, the summary: ``done_timestamp`` ...).
    rows : (N, 22) array
        The samples, ``COLUMNS``.
    closed : bool
        Whether the record is complete (its summary exists).
    """

    path: Path | None
    meta: dict[str, Any]
    rows: np.ndarray
    closed: bool

    @property
    def move(self) -> int:
        return int(self.meta["move"])

    @property
    def time(self) -> np.ndarray:
        """(N,) controller seconds."""
        return self.rows[:, 0]

    def _pose(self, first: int) -> np.ndarray:
        return _transforms(self.rows[:, first:first + 3], self.rows[:, first + 3:first + 7])

    def flange(self) -> np.ndarray:
        """(N, 4, 4) true flange poses in the base frame."""
        return self._pose(1)

    def commanded_tcp(self) -> np.ndarray:
        """(N, 4, 4) commanded TCP poses."""
        return self._pose(8)

    def encoder_tcp(self) -> np.ndarray:
        """(N, 4, 4) the TCP pose the encoders report (RTDE ``actual_TCP_pose``)."""
        return self._pose(15)

    def true_tcp(self) -> np.ndarray:
        """(N, 4, 4) true TCP poses (the flange with the record's TCP offset)."""
        from sim_devices._transforms import pose6_to_matrix

        return self.flange() @ pose6_to_matrix(self.meta["tcp_offset"])


def read_trajectory(path: str | Path) -> Trajectory:
    """One trajectory file (complete or still being written)."""
    path = Path(path)
    data = path.read_bytes()
    meta = json.loads(data[:HEADER_BYTES].decode())
    if meta.get("format") != FORMAT:
        raise ValueError(f"{path}: not a trajectory file ({meta.get('format')!r})")
    body = data[HEADER_BYTES:]
    usable = len(body) // (8 * WIDTH) * 8 * WIDTH
    rows = np.frombuffer(body[:usable], dtype="<f8").reshape(-1, WIDTH).copy()
    summary = path.with_suffix(".json")
    closed = summary.exists()
    if closed:
        try:
            meta = {**meta, **json.loads(summary.read_text())}
        except ValueError:
            closed = False  # being written
    return Trajectory(path, meta, rows, closed)


@dataclass
class TrajectoryLog:
    """Every trajectory record of a directory, for truth at any controller time.

    Parameters
    ----------
    directory : path
        ``<cell>/trajectories``.
    """

    directory: Path
    _cache: dict[Path, Trajectory] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.directory = Path(self.directory)

    def records(self) -> list[Trajectory]:
        """All records in move order (closed ones are read once; open ones again each call)."""
        out = []
        for path in sorted(self.directory.glob("move-*.traj")):
            cached = self._cache.get(path)
            if cached is None or not cached.closed:
                cached = read_trajectory(path)
                if cached.closed:
                    self._cache[path] = cached
            if len(cached.rows):
                out.append(cached)
        return out

    def clock(self) -> dict[str, Any] | None:
        """The controller clock's description (``clock.json``: ``monotonic_origin``, ``period``, ``time_scale``)."""
        try:
            return json.loads((self.directory / "clock.json").read_text())
        except (OSError, ValueError):
            return None

    def known_until(self) -> float:
        """Controller time up to which the truth is written: the last row of an open record, or +inf
        once every record is closed (the robot rests at the last record's final pose)."""
        records = self.records()
        if not records:
            return math.inf
        last = records[-1]
        return math.inf if last.closed else float(last.time[-1])

    def samples(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """The recorded samples from ``t0`` to ``t1`` (controller s) of every record: (times (n,),
        true flange poses (n, 4, 4)). Between records the robot rests (``flange_at`` fills that)."""
        times, poses = [], []
        for record in self.records():
            inside = (record.time >= t0) & (record.time <= t1)
            if np.any(inside):
                times.append(record.time[inside])
                poses.append(record.flange()[inside])
        if not times:
            return np.empty(0), np.empty((0, 4, 4))
        return np.concatenate(times), np.concatenate(poses)

    def flange_at(self, times, *, rest: np.ndarray | None = None) -> np.ndarray:
        """True flange poses (n, 4, 4) at controller ``times``.

        Inside a record: interpolated between its two samples around each time. Between records
        (or after the last one): the previous record's final pose. Before the first record:
        ``rest`` (the pose the robot started at), or the first record's first sample.
        """
        times = np.atleast_1d(np.asarray(times, dtype=float))
        records = self.records()
        out = np.empty((len(times), 4, 4))
        if not records:
            if rest is None:
                raise ValueError(f"no trajectory records in {self.directory}")
            out[:] = rest
            return out
        starts = np.array([r.time[0] for r in records])
        for i, t in enumerate(times):
            k = int(np.searchsorted(starts, t, side="right")) - 1
            if k < 0:
                out[i] = rest if rest is not None else records[0].flange()[0]
                continue
            out[i] = _interpolate(records[k], t)
        return out


def _interpolate(record: Trajectory, t: float) -> np.ndarray:
    time = record.time
    j = int(np.searchsorted(time, t, side="right"))
    if j >= len(time):
        j = len(time) - 1
        u = 0.0
        lo = hi = j
    elif j == 0:
        lo = hi = 0
        u = 0.0
    else:
        lo, hi = j - 1, j
        u = (t - time[lo]) / (time[hi] - time[lo])
    a, b = record.rows[lo], record.rows[hi]
    position = a[1:4] + u * (b[1:4] - a[1:4])
    qa, qb = a[4:8], b[4:8]
    if qa @ qb < 0:
        qb = -qb
    q = qa + u * (qb - qa)
    return _transforms(position[None], q[None])[0]


def true_poses_in_m(world: Any, flange: np.ndarray, point: str = "opr") -> np.ndarray:
    """(n, 4, 4) true poses in M of the OPR (``point="opr"``) or of the ISO tool point (``"tool"``)
    for true flange poses (n, 4, 4), with the world's true mounting constants."""
    from sim_devices._transforms import invert

    tail = world.true_opr_mount if point == "opr" else world.true_tool
    if point not in ("opr", "tool"):
        raise ValueError(f"point must be 'opr' or 'tool', got {point!r}")
    return invert(world.base_to_m)[None] @ flange @ tail[None]


__all__ = ["COLUMNS", "FORMAT", "HEADER_BYTES", "Trajectory", "TrajectoryLog", "read_trajectory",
           "true_poses_in_m"]
