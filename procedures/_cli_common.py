"""Shared pieces of the run-related subcommands: the runs folder, the terminal display, Ctrl-C."""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from procedures._errors import RunError
from procedures._run_state import PauseDecision, RunState
from procedures._store import RunStore

if TYPE_CHECKING:  # only for annotations: the engine's stack loads with the commands that run one
    from procedures._engine import RunEngine

EXIT_CODES = {RunState.FINISHED: 0, RunState.FAILED: 1, RunState.ABORTED: 2, RunState.PAUSED: 3}


def add_runs_dir(parser) -> None:
    parser.add_argument("--runs-dir", default=os.environ.get("INSTRUMENT_RUNS", "runs"),
                        help="runs folder holding runs.sqlite (default: $INSTRUMENT_RUNS or ./runs)")


def add_display(parser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--quiet", action="store_true", help="print only the final state")
    group.add_argument("--jsonl", action="store_true", help="one JSON event per line on stdout (for automation)")


def open_store(args) -> RunStore:
    path = Path(args.runs_dir)
    if not (path / "runs.sqlite").is_file():
        raise SystemExit(f"no run store in {path} (use --runs-dir or $INSTRUMENT_RUNS)")
    return RunStore(path)


def find_run(store: RunStore, run_id: str) -> dict | None:
    """The stored run ``run_id``, or None after saying on stderr why there is none."""
    try:
        return store.get_run(run_id)
    except KeyError as exc:
        print(exc.args[0], file=sys.stderr)
        return None


def _clock(seconds: float | None) -> str:
    if seconds is None:
        return "--:--"
    seconds = int(seconds)
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


class Display:
    """Progress bar with ETA and a live line with the last pose and its quality (on stderr),
    or JSON lines on stdout, or nothing."""

    def __init__(self, mode: str = "bar", stream=None) -> None:
        self.mode = mode
        self.stream = stream or sys.stderr
        self.last = ""

    def __call__(self, event: dict) -> None:
        if self.mode == "jsonl":
            print(json.dumps(event, default=str), flush=True)
            return
        if self.mode == "quiet":
            return
        kind = event["event"]
        if kind == "point_measured":
            pose = event.get("pose")
            if event.get("ok") and pose:
                self.last = (f"{event['label']}: x {pose[0] * 1e3:.4f} y {pose[1] * 1e3:.4f} z {pose[2] * 1e3:.4f} mm  "
                             f"residual {(event.get('residual_rms') or 0) * 1e6:.2f} µm")
            else:
                self.last = f"{event['label']}: FAILED {event.get('error')}"
        elif kind == "progress":
            done, total = event["done"], event["total"]
            width = 30
            filled = int(width * done / max(total, 1))
            line = (f"[{'#' * filled}{'.' * (width - filled)}] {done}/{total} {100 * done / max(total, 1):3.0f}% "
                    f"ETA {_clock(event.get('eta_s'))} | {self.last}")
            print("\r" + line[:150].ljust(150), end="", file=self.stream, flush=True)
        elif kind == "state":
            print(
                f"\n{time.strftime('%H:%M:%S')} {event['state']}"
                + (f": {event['reason']}" if event.get("reason") else ""),
                file=self.stream,
                flush=True,
            )
        elif kind == "dry_run":
            problems = event.get("problems") or []
            print(f"dry run: {event['steps']} steps checked, {len(problems)} problems", file=self.stream, flush=True)
        elif kind == "setup":
            print(f"\nset-up: {event['setup']}", file=self.stream, flush=True)


_ANSWERS: dict[str, PauseDecision] = {"": "resume", "a": "abort", "q": "detach"}


def console_pause_handler(engine: RunEngine) -> PauseDecision:
    """Ask the operator what to do with a paused run."""
    if not sys.stdin.isatty():
        return "detach"
    print("\nrun paused. [Enter] resume, [a] abort, [q] quit and leave it paused (instrument resume RUN)",
          file=sys.stderr)
    answer = input("> ").strip().lower()
    return _ANSWERS.get(answer, "detach")


@contextmanager
def ctrl_c_pauses(engine: RunEngine) -> Iterator[None]:
    """First Ctrl-C: pause at the next safe point. Second: abort now (KeyboardInterrupt)."""
    presses = {"count": 0}

    def handler(signum, frame):
        presses["count"] += 1
        if presses["count"] == 1:
            print("\nCtrl-C: pausing at the next safe point (Ctrl-C again aborts)", file=sys.stderr, flush=True)
            engine.request_pause("Ctrl-C")
        else:
            signal.signal(signal.SIGINT, signal.default_int_handler)
            raise KeyboardInterrupt("aborted by a second Ctrl-C")

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextmanager
def station_for(station: str | None, runs_dir: Path, seed: int) -> Iterator[str | None]:
    """``sim`` starts the simulated cell for the run (its files kept under the runs folder)."""
    if station != "sim":
        yield station
        return
    from sim_devices.cell import SimCell

    directory = Path(runs_dir) / "sim" / time.strftime("%Y%m%d-%H%M%S")
    directory.mkdir(parents=True, exist_ok=True)
    cell = SimCell(seed=seed, directory=directory)
    try:
        cell.start()
    except Exception as exc:  # the twins' own message, without their traceback
        cell.stop()
        raise RunError(f"the simulated cell did not start: {str(exc).strip().splitlines()[-1]}") from None
    try:
        yield str(cell.station_path)
    finally:
        cell.stop()


def drive(engine: RunEngine, args: argparse.Namespace) -> int:
    """Execute with the display and Ctrl-C handling; print the outcome; return the exit code."""
    with ctrl_c_pauses(engine):
        state = engine.execute()
    run = engine.store.get_run(engine.run_id)
    if args.jsonl:
        print(json.dumps({"event": "done", "run_id": engine.run_id, "state": state, "reason": run["reason"]}))
    else:
        print(f"\nrun {engine.run_id}: {state}" + (f" — {run['reason']}" if run["reason"] else ""), file=sys.stderr)
        if args.quiet:
            print(f"{engine.run_id} {state}")
    return EXIT_CODES.get(state, 1)
