"""Read access to the run store for the web view and the OPC UA server.

The engine writes the store (SQLite in WAL mode, or a shared PostgreSQL) from another process; a reader
sees each committed sample and event as it lands. ``StoreReader.version()`` is the store's change
counter read on a connection of its own (SQLite's ``PRAGMA data_version``; PostgreSQL's
``store_changes`` row, bumped in every writing transaction): it changes when another connection
commits, so a server polls it a few times a second for next to nothing and reads the runs again only
when something changed. Everything handed
out here is JSON-able and in SI units (m, rad, s); the pages convert at their edge.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from procedures.report import report_title
from procedures.store import RunState, RunStore, Sample

T = TypeVar("T")

ACTIVE_STATES = (RunState.RUNNING, RunState.PAUSED, RunState.QUEUED)


def robot_of(run: dict[str, Any]) -> dict[str, str]:
    """Whose robot a run measured: ``{"key", "label", "source"}``.

    Runs that record the robot's identity (``robot_serial`` … read from the controller at run start)
    are grouped by serial number, whichever station they ran on; older runs (no identity) by station
    name; ``source`` says which of the two it is.
    """
    serial = run.get("robot_serial")
    if serial:
        model = " ".join(part for part in (run.get("robot_manufacturer"), run.get("robot_model")) if part) or "robot"
        return {"key": f"serial:{serial}", "label": f"{model} serial {serial}", "source": "identity"}
    station = run.get("station_name") or "unnamed station"
    return {"key": f"station:{station}", "label": station, "source": "station"}


def run_summary(run: dict[str, Any]) -> dict[str, Any]:
    """The columns of a ``RunStore.list_runs`` row every page shows, JSON-able."""
    return {
        "id": run["id"],
        "procedure": run["procedure"],
        "name": run.get("procedure_name"),
        # As the run's kind words it from the parameters in force (``--set cycles=3``: "3 cycles"), never the
        # procedure file's name; the results' own count once the run has them.
        "title": report_title(run),
        "station": run.get("station_name"),
        "state": str(RunState(run["state"]).value),
        "reason": run.get("reason"),
        "created": run.get("created"),
        "started": run.get("started"),
        "finished": run.get("finished"),
        "total": run.get("total_steps"),
        "done": run.get("samples"),
        "robot": robot_of(run),
    }


def point_of(sample: Sample) -> dict[str, Any]:
    """One committed sample as the live page plots it: the attained pose (corrected when the run
    corrects, else solved; m and rad, ``[x, y, z, a, b, c]`` in M) and its quality."""
    meta = sample.meta
    return {
        "step": sample.step_index,
        "key": sample.step_key,
        "label": sample.label,
        "phase": sample.phase,
        "cycle": meta.get("cycle"),
        "ok": sample.ok,
        "error": sample.error,
        "pose": None if sample.pose is None else list(sample.pose),
        "residual_rms": None if sample.quality is None else sample.quality.residual_rms,
        "time": sample.t_committed,
    }


class StoreReader:
    """Thread-safe read access to the store in ``runs_dir`` (created if it does not exist yet).

    Parameters
    ----------
    runs_dir : folder holding ``runs.sqlite``
    cache_size : how many (run, store version) snapshots are kept, so that many pages following
        one run cost one read of the store per change
    """

    def __init__(self, runs_dir: str | Path, *, cache_size: int = 64) -> None:
        self.runs_dir = Path(runs_dir)
        self._store = RunStore(self.runs_dir)
        self._lock = threading.Lock()
        # A connection of its own for the change counter (SQLite's counts the commits of *other* connections).
        self._probe = RunStore(self.runs_dir, timeout=5.0)
        self._cache: OrderedDict[tuple[str, str, int], Any] = OrderedDict()
        self._cache_size = cache_size

    def close(self) -> None:
        with self._lock:
            self._probe.close()
            self._store.close()

    def version(self) -> int:
        """A number that changes whenever another connection (the engine, a resume) commits."""
        with self._lock:
            return self._probe.version()

    def _cached(self, what: str, key: str, compute: Callable[[], T]) -> T:
        """``compute()`` once per store version."""
        cache_key = (what, key, self.version())
        with self._lock:
            if cache_key in self._cache:
                self._cache.move_to_end(cache_key)
                return self._cache[cache_key]
        value = compute()
        with self._lock:
            self._cache[cache_key] = value
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return value

    # ------------------------------------------------------------------------------ plain reads
    def runs(self) -> list[dict[str, Any]]:
        """Every run, newest first (``run_summary`` rows)."""
        def compute() -> list[dict[str, Any]]:
            with self._lock:
                rows = self._store.list_runs()
                parameters = self._store.parameters_of()
            return [run_summary({**row, "parameters": parameters.get(row["id"], {})}) for row in reversed(rows)]
        return self._cached("runs", "", compute)

    def run(self, run_id: str) -> dict[str, Any]:
        """The whole run row (JSON fields decoded); ``run_id`` may be a unique prefix. Raises ``KeyError``."""
        with self._lock:
            run = self._store.get_run(run_id)
        run["state"] = str(run["state"].value)
        return run

    def samples(self, run_id: str) -> list[Sample]:
        with self._lock:
            return self._store.samples(run_id)

    def events(self, run_id: str) -> list[dict[str, Any]]:
        with self._lock:
            return self._store.events(run_id)

    def latest_stream(self, run_id: str) -> dict[str, Any] | None:
        """The newest stored pose stream of a run measured in motion (None: it has none), for the live
        page's panel: ``step``, ``key``, ``t`` (s from the robot's done signal), ``distance`` (m, to the
        attained pose: the mean of the stream's last fifth), ``rate_hz``, ``dropped``, ``poses``."""
        from procedures.kinds import StreamRecord

        def compute() -> dict[str, Any] | None:
            with self._lock:
                steps = self._store.stream_steps(run_id)
                if not steps:
                    return None
                stored = self._store.streams(run_id, [steps[-1]])[steps[-1]]
                keys = {s.step_index: s.step_key for s in self._store.samples(run_id)}
            record = StreamRecord.from_stored(stored)
            if not len(record):
                return None
            attained = record.pose[-max(3, len(record) // 5):, :3].mean(axis=0)
            signal = record.meta.get("t_signal")
            origin = float(signal) if signal is not None else float(record.t[0])
            return {"step": steps[-1], "key": keys.get(steps[-1]), "t": (record.t - origin).tolist(),
                    "distance": np.linalg.norm(record.pose[:, :3] - attained, axis=1).tolist(),
                    "rate_hz": record.meta.get("rate_hz"), "dropped": record.dropped, "poses": len(record)}
        return self._cached("posestream", run_id, compute)

    def current_run_id(self) -> str | None:
        """The run a live view follows: the newest running, paused or queued run, else the newest run."""
        runs = self.runs()
        for run in runs:
            if run["state"] in ACTIVE_STATES:
                return str(run["id"])
        return str(runs[0]["id"]) if runs else None

    # ------------------------------------------------------------------------------- snapshots
    def snapshot(self, run_id: str) -> dict[str, Any]:
        """What a live page shows of one run, read once per store version: ``run`` (summary plus
        phase, cycle and ETA), ``points`` (every committed sample, ``point_of``), ``events``,
        ``samples`` (the decoded samples, for the frames). Raises ``KeyError`` for an unknown run."""
        def compute() -> dict[str, Any]:
            run = self.run(run_id)
            samples = self.samples(run["id"])
            events = self.events(run["id"])
            summary = run_summary({**run, "samples": len(samples)})
            summary.update(progress_of(samples, run.get("total_steps")))
            return {"run": summary, "results": run.get("results"), "points": [point_of(s) for s in samples],
                    "events": [{"time": e["time"], "kind": e["kind"], "message": e["message"]} for e in events],
                    "samples": samples}
        return self._cached("snapshot", run_id, compute)

    def iso_history(self, robot_key: str) -> list[dict[str, Any]]:
        """The finished ISO 9283 runs of one robot (``robot_of(run)["key"]``: its serial when the runs
        carry it), oldest first: per point n, RP and AP with their confidence intervals (SI), and
        ``uncertainty`` (key → U, or the interval's half-width) and ``changed`` (key → Δ from the
        robot's previous run, where it exceeds both runs' uncertainties combined; ``instrument history``).
        The runs are those of the kinds that declare ``history_figures``."""
        from procedures.report import changes, history_figures, history_procedures, iso_points, iso_rows

        def compute() -> list[dict[str, Any]]:
            history: list[dict[str, Any]] = []
            previous: dict[str, dict[str, Any]] = {}
            followed, keys = history_procedures(), history_figures()
            for summary in reversed(self.runs()):
                if summary["robot"]["key"] != robot_key or summary["procedure"] not in followed:
                    continue
                if summary["state"] != RunState.FINISHED:
                    continue
                results = self.run(summary["id"]).get("results") or {}
                points = iso_points(results)
                for row in iso_rows(results, keys):
                    figures = {key: row[key] for key in keys}
                    if row["point"] in points:
                        points[row["point"]]["uncertainty"] = {key: fig["u"] for key, fig in figures.items()
                                                               if fig and fig["u"] is not None}
                        points[row["point"]]["changed"] = changes(previous.get(row["point"]), figures)
                    previous[row["point"]] = figures
                history.append({"run": summary, "points": points})
            return history
        return self._cached("history", robot_key, compute)


def progress_of(samples: list[Sample], total: int | None) -> dict[str, Any]:
    """Phase and cycle of the newest sample, and an ETA from the pace of the last 20 samples (s)."""
    newest = max(samples, key=lambda s: s.t_committed or 0.0) if samples else None
    times = sorted(s.t_committed for s in samples if s.t_committed is not None)[-21:]
    pace = (times[-1] - times[0]) / (len(times) - 1) if len(times) >= 2 else None
    remaining = max((total or 0) - len(samples), 0)
    return {
        "phase": newest.phase if newest else None,
        "cycle": newest.meta.get("cycle") if newest else None,
        "label": newest.label if newest else None,
        "failed": sum(1 for s in samples if not s.ok),
        "eta_s": pace * remaining if pace is not None else None,
        "last_time": newest.t_committed if newest else None,
    }
