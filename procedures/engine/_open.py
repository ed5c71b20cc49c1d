"""Start or continue a run in a few lines (what the CLI and the tests use).

>>> with open_engine("runs", procedure="iso9283_repeatability", station="station.yaml") as engine:
...     state = engine.execute()
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from procedures.engine._engine import PauseDecision, RunEngine, create_run
from procedures.engine._hooks import HookRunner
from procedures.engine._loading import load_procedure, load_station, resolve_procedure_path
from procedures.engine._overrides import apply_overrides
from procedures.station import (
    ConfigError,
    HookSpec,
    InputRefused,
    InstrumentScience,
    Operator,
    RunError,
    Science,
    StationFile,
    StationRuntime,
    read_text_file,
)
from procedures.store import Lease, RunStore, StoreError


def with_earlier_truth(station: StationFile, before: StationFile) -> StationFile:
    """``station`` (a new simulated cell for a resumed run) remembering the truth logs of the cells
    the run was measured on ``before``, so its report keeps the truth of every sample."""
    if station.simulation is None or before.simulation is None:
        return station
    earlier = [*before.simulation.earlier_truth_logs, before.simulation.truth_log,
               *station.simulation.earlier_truth_logs]
    kept = [path for i, path in enumerate(earlier)
            if path and path not in earlier[:i] and path != station.simulation.truth_log]
    simulation = station.simulation.model_copy(update={"earlier_truth_logs": kept})
    return station.model_copy(update={"simulation": simulation})


@contextmanager
def open_engine(
    runs_dir: str | Path,
    *,
    procedure: str | Path | None = None,
    station: str | Path | None = None,
    run_id: str | None = None,
    science: Science | None = None,
    devices: dict[str, Any] | None = None,
    operator: Operator | None = None,
    listener: Callable[[dict[str, Any]], None] | None = None,
    pause_handler: Callable[[RunEngine], PauseDecision] | None = None,
    pause_timeout_s: float = 3600.0,
    extra_hooks: Sequence[HookSpec] = (),
    store: str | None = None,
    overrides: Sequence[str] = (),
) -> Iterator[RunEngine]:
    """A ``RunEngine`` for a new run (``procedure`` + ``station``) or a stored one (``run_id``).

    On resume the station snapshot stored with the run is used, unless ``station`` names a file
    (e.g. a freshly started simulated cell); its frames and envelope must equal the snapshot's.
    The process holds the run's lease for the whole block (``RunLocked`` if another live process
    does). Devices are closed (after the engine has brought them to a safe state) when the block ends.

    ``store`` is a ``postgresql://`` URL of a shared run store (default ``$INSTRUMENT_STORE``, else the
    runs folder's SQLite file; per-run files stay in ``runs_dir`` either way). ``overrides``
    (``"key=value"``, a new run only) change the procedure's parameters; the stored procedure text
    holds them (``procedures.engine._overrides``).
    """
    if overrides and run_id is not None:
        raise RunError("parameter overrides (--set) apply to a new run only; a resumed run keeps its own")
    run_store = RunStore(runs_dir, url=store)
    runtime = None
    lease: Lease | None = None
    try:
        # A custom science (a test's fake) has no geometry to judge the station's with.
        custom_science = science is not None
        science = science if science is not None else InstrumentScience()
        if run_id is None:
            if procedure is None or station is None:
                raise RunError("a new run needs a procedure and a station")
            procedure_path = resolve_procedure_path(procedure)
            try:
                text = read_text_file(procedure_path, what="procedure file")
            except InputRefused as exc:
                raise ConfigError([str(exc)]) from None
            if overrides:
                text, proc = apply_overrides(procedure_path, text, list(overrides))
            else:
                proc = load_procedure(procedure_path, text)
            station_model = load_station(station, check_geometry=not custom_science)
            runtime = StationRuntime(station_model, devices=devices, operator=operator)
            run_id = create_run(run_store, proc, runtime, science, procedure_file=str(procedure_path.resolve()),
                                procedure_text=text, station_path=str(Path(station).resolve()))
            lease = run_store.acquire_lease(run_id)
        else:
            run = run_store.get_run(run_id)
            run_id = str(run["id"])
            lease = run_store.acquire_lease(run_id)  # before anything of the run is touched
            proc = load_procedure(run["procedure_file"] or f"run {run_id}", run["procedure_text"], stored=True)
            snapshot = StationFile.model_validate(run["station"])
            if station is not None:
                station_model = load_station(station, check_geometry=not custom_science)
                for part in ("frames", "envelope"):
                    if getattr(station_model, part) != getattr(snapshot, part):
                        raise RunError(f"station {station}: its {part} differ from the run's snapshot; "
                                       "resume on the station the run started on")
                station_model = with_earlier_truth(station_model, snapshot)
                run_store.update_run(run_id, station=station_model.model_dump(),
                                     station_path=str(Path(station).resolve()))
            else:
                station_model = snapshot
            runtime = StationRuntime(station_model, devices=devices, operator=operator)
        hooks = HookRunner([*station_model.hooks, *proc.hooks, *extra_hooks])
        engine = RunEngine(run_store, run_id, proc, runtime, science, hooks=hooks, listener=listener,
                           pause_handler=pause_handler, pause_timeout_s=pause_timeout_s, lease=lease)
        yield engine
    finally:
        try:
            if runtime is not None:
                runtime.safe_state()
                runtime.close()
        finally:
            if lease is not None:
                try:
                    run_store.release_lease(lease)
                except StoreError:
                    pass  # a full, locked or damaged store (the outcome says so): a dead pid's lease is taken over
            run_store.close()
