"""The simulated cell's truth for a streamed move: the robot twin's dense trajectory (1 kHz) at the
stream's instants, as the OPR's pose in M.

The twin writes one trajectory file per move into ``<cell>/trajectories`` (``sim_devices.trajectory``:
the true flange pose on the controller's clock), beside the cell's truth log (``truth.jsonl``),
whose ``cell`` entry holds the world's true constants (``base_to_m``, ``true_opr_mount``, UR poses).
So the truth of a move is kept like the static kinds keep theirs, in the cell's folder, and a
resumed run's earlier cells keep theirs (``simulation.earlier_truth_logs``). The true OPR pose in M
is ``inv(base_to_m) · flange · true_opr_mount``; the analysis puts the nominal tool offset on it,
as the static kind does for its "true" rows, so that measured and true figures differ only by the
instrument's error.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from procedures.station import matrix_to_euler, ur_to_matrix


class MoveTruth:
    """The truth of one simulated cell (its truth log and its trajectory files)."""

    def __init__(self, truth_log: str | Path) -> None:
        self.truth_log = Path(truth_log)
        self.constants = _cell_constants(self.truth_log)
        self._log: Any = None

    @property
    def available(self) -> bool:
        return self.constants is not None and (self.truth_log.parent / "trajectories").is_dir()

    def _trajectories(self) -> Any:
        if self._log is None:
            from sim_devices.trajectory import TrajectoryLog  # only for a simulated cell's truth

            self._log = TrajectoryLog(self.truth_log.parent / "trajectories")
        return self._log

    def opr_in_m(self, times: np.ndarray) -> np.ndarray:
        """(n, 6) true OPR poses in M [x, y, z, a, b, c] at controller ``times`` (s)."""
        assert self.constants is not None
        flange = self._trajectories().flange_at(np.asarray(times, dtype=float))
        m_from_base = np.linalg.inv(ur_to_matrix(self.constants["base_to_m"]))
        mount = ur_to_matrix(self.constants["true_opr_mount"])
        return np.array([matrix_to_euler(m_from_base @ f @ mount) for f in flange])

    def dense(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """The recorded truth samples (1 kHz) from ``t0`` to ``t1``: (times (n,), OPR poses in M (n, 6))."""
        assert self.constants is not None
        times, flange = self._trajectories().samples(t0, t1)
        m_from_base = np.linalg.inv(ur_to_matrix(self.constants["base_to_m"]))
        mount = ur_to_matrix(self.constants["true_opr_mount"])
        return times, np.array([matrix_to_euler(m_from_base @ f @ mount) for f in flange]).reshape(-1, 6)


def _cell_constants(truth_log: Path) -> dict[str, Any] | None:
    try:
        with open(truth_log, encoding="utf-8", errors="replace") as handle:
            for line in handle:
                if '"cell"' not in line:
                    continue
                try:
                    entry = json.loads(line)
                except json.JSONDecodeError:
                    continue
                if entry.get("event") == "cell" and "describe" in entry:
                    describe = entry["describe"]
                    return {"base_to_m": describe["base_to_m"], "true_opr_mount": describe["true_opr_mount"]}
    except OSError:
        return None
    return None


def truths_of(station_simulation: Any) -> dict[str, MoveTruth]:
    """Every cell's truth the run may have been measured on, by truth-log path."""
    if station_simulation is None:
        return {}
    paths = [p for p in [*station_simulation.earlier_truth_logs, station_simulation.truth_log] if p]
    out = {}
    for path in paths:
        truth = MoveTruth(path)
        if truth.available:
            out[str(path)] = truth
    return out
