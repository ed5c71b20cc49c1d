"""Runs started for a cell controller: each one an ``instrument run … --jsonl`` child process.

The engine is not changed for this: the launcher drives the CLI as an operator would. Start checks the
procedure with its overrides as ``instrument run`` will and spawns ``instrument run PROCEDURE --station
STATION --set KEY=VALUE ... --jsonl --pause-timeout 0`` (the run folder shared with the server; no file is
written for a run, refused or not); Pause sends the child SIGINT (one Ctrl-C: the engine pauses at the
next safe point, and without a terminal a paused run is left PAUSED in the store and the process exits 3); Resume spawns
``instrument resume RUN --jsonl``; Abort sends SIGTERM (an abort: devices stopped, ABORTED stored), and
if the process ended without storing an outcome, or the run was paused with no process, the launcher
stores ABORTED itself. Every child runs in its own session (a Ctrl-C at the server's terminal does not
reach it) and is stopped when the launcher closes.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from procedures.engine import apply_overrides, load_procedure, resolve_procedure_path
from procedures.station import ConfigError, InputRefused, RunLocked, StateConflict, read_text_file
from procedures.store import RunState, RunStore


class LaunchRefused(ValueError):
    """A request the launcher cannot carry out now; the message says why, in one line."""


def parse_overrides(text: str) -> dict[str, Any]:
    """``"cycles=5; settle_time_s=0.05"`` → ``{"cycles": 5, "settle_time_s": 0.05}``.

    Pairs are separated by ``;`` or new lines (a value may hold commas: ``cube_center_m=[0.03, 0.03, 0.03]``);
    each value is read as a YAML scalar or list, as it would be in the procedure file.
    """
    overrides: dict[str, Any] = {}
    for part in text.replace("\n", ";").split(";"):
        if not part.strip():
            continue
        key, sep, value = part.partition("=")
        if not sep or not key.strip():
            raise LaunchRefused(f"override {part.strip()!r}: expected key=value")
        try:
            overrides[key.strip()] = yaml.safe_load(value)
        except yaml.YAMLError:
            raise LaunchRefused(f"override {key.strip()}: cannot read value {value.strip()!r}") from None
    return overrides


def override_items(text: str) -> list[str]:
    """``"cycles=5; settle_time_s=0.05"`` → ``["cycles=5", "settle_time_s=0.05"]``: the ``--set`` values of the run
    (separated as in ``parse_overrides``). Raises ``LaunchRefused`` for a part that is no ``key=value``."""
    parse_overrides(text)  # the same refusals, in the same words
    items = []
    for part in text.replace("\n", ";").split(";"):
        key, sep, value = part.partition("=")
        if sep:
            items.append(f"{key.strip()}={value.strip()}")
    return items


def checked_procedure(procedure: str, items: list[str]) -> Path:
    """The procedure file to run, checked with its ``--set`` ``items`` exactly as ``instrument run`` will
    (``procedures.engine.apply_overrides``); nothing is written. Raises ``LaunchRefused`` with the problems."""
    try:
        path = resolve_procedure_path(procedure)
        text = read_text_file(path, what="procedure file")
    except (ConfigError, InputRefused) as exc:
        raise LaunchRefused(str(exc).splitlines()[0] if str(exc) else f"no procedure {procedure!r}") from None
    try:
        if items:
            apply_overrides(path, text, items)
        else:
            load_procedure(path, text)
    except ConfigError as exc:
        raise LaunchRefused("; ".join(str(exc).splitlines())) from None
    return path


@dataclass
class Launch:
    """One child process and what it said (``--jsonl`` events)."""

    command: list[str]
    station: str
    process: asyncio.subprocess.Process
    log_path: Path
    run_id: str | None = None
    last_event: dict[str, Any] = field(default_factory=dict)
    abort_requested: bool = False
    exit_code: int | None = None
    reader: asyncio.Task[None] | None = None

    @property
    def alive(self) -> bool:
        return self.exit_code is None


class RunLauncher:
    """Starts, pauses, resumes and aborts runs as child processes; one run at a time.

    Parameters
    ----------
    runs_dir : the runs folder shared with the children
    python : the interpreter of the children (``python -m procedures`` is the CLI)
    on_problem : called with one line when something goes wrong out of a request (a child that died)
    """

    def __init__(self, runs_dir: str | Path, *, python: str = sys.executable,
                 on_problem: Any = None) -> None:
        self.runs_dir = Path(runs_dir)
        self.python = python
        self.on_problem = on_problem or (lambda message: None)
        self.launches: list[Launch] = []
        self._stations: dict[str, str] = {}  # run id → the --station it was started with

    @property
    def active(self) -> Launch | None:
        """The child still running, if any."""
        return next((launch for launch in reversed(self.launches) if launch.alive), None)

    @property
    def starting(self) -> bool:
        """A child is running but has not yet said which run it is."""
        launch = self.active
        return launch is not None and launch.run_id is None

    async def start_run(self, procedure: str, station: str, overrides: str = "") -> Launch:
        """Validate and start a run (``station``: a station file or ``sim``). Raises ``LaunchRefused``."""
        if self.active is not None:
            raise LaunchRefused("a run started here is still going; pause, abort or wait for it first")
        if station != "sim" and not Path(station).is_file():
            raise LaunchRefused(f"no station file {station!r} (give a station YAML or 'sim')")
        items = override_items(overrides)
        path = checked_procedure(procedure, items)
        # The overrides go to the run as --set (stored with it, as from a terminal); no copy of the file is made.
        command = ["run", str(path), "--station", station, *[f"--set={item}" for item in items]]
        return await self._spawn(command, station)

    async def resume(self, run_id: str) -> Launch:
        """Continue a paused or interrupted run in a new child. Raises ``LaunchRefused``."""
        if self.active is not None:
            raise LaunchRefused("a run started here is still going")
        station = self._stations.get(run_id)
        command = ["resume", run_id] + (["--station", "sim"] if station == "sim" else [])
        return await self._spawn(command, station or "")

    def pause(self) -> None:
        """One Ctrl-C to the running child: it pauses at the next safe point, then exits (PAUSED stored)."""
        launch = self.active
        if launch is None or launch.run_id is None:
            raise LaunchRefused("no run started here is running")
        launch.process.send_signal(signal.SIGINT)

    def abort(self, paused_run_id: str | None = None) -> None:
        """SIGTERM to the running child; with no child, store a paused run ``paused_run_id`` as ABORTED."""
        launch = self.active
        if launch is not None:
            launch.abort_requested = True
            launch.process.send_signal(signal.SIGTERM)
            return
        if paused_run_id is None:
            raise LaunchRefused("nothing to abort: no run started here is running, and no run is paused")
        _store_aborted(self.runs_dir, paused_run_id, "aborted by the cell controller while paused")

    async def close(self, timeout: float = 20.0) -> None:
        """Stop every child (SIGTERM, then SIGKILL after ``timeout`` s) and wait for it."""
        for launch in self.launches:
            if launch.alive:
                launch.abort_requested = True
                with contextlib.suppress(ProcessLookupError):
                    launch.process.send_signal(signal.SIGTERM)
        for launch in self.launches:
            if launch.reader is None:
                continue
            try:
                await asyncio.wait_for(asyncio.shield(launch.reader), timeout)
            except TimeoutError:
                with contextlib.suppress(ProcessLookupError):
                    launch.process.kill()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(launch.reader, 5.0)

    # ------------------------------------------------------------------------------------ inside
    async def _spawn(self, command: list[str], station: str) -> Launch:
        log_dir = self.runs_dir / "serve"
        log_dir.mkdir(parents=True, exist_ok=True)
        log_path = log_dir / f"{time.strftime('%Y%m%d-%H%M%S')}-{command[0]}-{len(self.launches)}.log"
        full = [self.python, "-m", "procedures", *command, "--jsonl", "--pause-timeout", "0",
                "--runs-dir", str(self.runs_dir)]
        with open(log_path, "wb") as log:  # the child's stderr; the file stays open in the child
            process = await asyncio.create_subprocess_exec(*full, stdin=asyncio.subprocess.DEVNULL,
                                                           stdout=asyncio.subprocess.PIPE, stderr=log,
                                                           start_new_session=True)
        launch = Launch(command=full, station=station, process=process, log_path=log_path)
        if command[0] == "resume":
            launch.run_id = command[1]
        launch.reader = asyncio.create_task(self._follow(launch))
        self.launches.append(launch)
        return launch

    async def _follow(self, launch: Launch) -> None:
        """Read the child's JSON lines (its run id, its last event) until it exits, then settle its run."""
        assert launch.process.stdout is not None
        async for raw in launch.process.stdout:
            try:
                event = json.loads(raw)
            except ValueError:
                continue
            if isinstance(event, dict):
                launch.last_event = event
                if launch.run_id is None and event.get("run_id"):
                    launch.run_id = str(event["run_id"])
                    self._stations[launch.run_id] = launch.station
        launch.exit_code = await launch.process.wait()
        if launch.exit_code not in (0, 1, 2, 3):
            tail = _last_line(launch.log_path)
            self.on_problem(f"run process exited with {launch.exit_code}" + (f": {tail}" if tail else ""))
        elif launch.exit_code == 1 and launch.run_id is None:
            self.on_problem(f"run did not start: {_last_line(launch.log_path) or 'see ' + str(launch.log_path)}")
        if launch.abort_requested and launch.run_id is not None:
            _store_aborted(self.runs_dir, launch.run_id, "aborted by the cell controller")


def _store_aborted(runs_dir: Path, run_id: str, reason: str) -> None:
    """Store ABORTED for a run left RUNNING, QUEUED or PAUSED by a process that is gone."""
    with RunStore(runs_dir) as store:
        run = store.get_run(run_id)
        state = RunState(run["state"])
        if state.ended:
            return
        # Take the run's lease first: a live process still holding it (a resume started meanwhile)
        # keeps its run; a dead one's lease is stale and taken over. Then compare-and-set.
        try:
            lease = store.acquire_lease(run["id"])
        except RunLocked:
            return
        try:
            store.set_state(run["id"], RunState.ABORTED, reason=reason, expected=state, lease=lease)
        except StateConflict:
            pass  # the state moved on under us: whoever moved it stored the truth
        finally:
            store.release_lease(lease)


def _last_line(path: Path) -> str:
    try:
        lines = [line for line in path.read_text(encoding="utf-8", errors="replace").splitlines() if line.strip()]
    except OSError:
        return ""
    return lines[-1].strip() if lines else ""
