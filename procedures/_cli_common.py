"""Shared pieces of the run-related subcommands: the runs folder, the terminal display, signals.

Signals while a run runs (``signals_control``): the first Ctrl-C pauses at the next safe point, a
second one (before the run has resumed from that pause) aborts at once; the count starts again at
every resume, however many pauses there were. SIGTERM and SIGHUP abort like a second Ctrl-C: the
robot and the table are sent ``stop()``, the run is stored ABORTED with the signal as its reason.
Signals that arrive while an abort is being recorded are ignored, so the abort always completes.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import tempfile
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


def add_seed(parser, default: int | None) -> None:
    parser.add_argument("--seed", type=seed_value, default=default,
                        help="simulated cell seed, 0 .. 2**32-1" + (f" (default {default})" if default is not None
                                                                    else " (default: the run's)"))


def seed_value(text: str) -> int:
    """An argparse type: a seed the twins' random generators take."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"expected 0 .. {2**32 - 1}, got {text[:20]}{'...' if len(text) > 20 else ''}")
    return value


def seconds_value(text: str) -> float:
    """An argparse type: a finite, non-negative number of seconds."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"expected a finite number of seconds ≥ 0, got {text!r}")
    return value


def open_store(args) -> RunStore:
    path = Path(args.runs_dir)
    if not (path / "runs.sqlite").is_file():
        raise RunError(f"no run store in {path} (use --runs-dir or $INSTRUMENT_RUNS)")
    return RunStore(path)


def write_output(path: str | Path, text: str) -> None:
    """Write a command's output file; a folder that does not exist or a refused write is one line."""
    try:
        Path(path).write_text(text, encoding="utf-8")
    except OSError as exc:
        raise RunError(f"cannot write {path}: {exc.strerror or exc}") from None


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
    """Ask the operator what to do with a paused run (without a terminal: leave it paused)."""
    if not sys.stdin.isatty():
        return "detach"
    print("\nrun paused. [Enter] resume, [a] abort, [q] quit and leave it paused (instrument resume RUN)",
          file=sys.stderr)
    try:
        answer = input("> ").strip().lower()
    except EOFError:
        return "detach"
    return _ANSWERS.get(answer, "detach")


def detach_at_once(engine: RunEngine) -> PauseDecision:
    """For ``--jsonl``: a paused run stays PAUSED in the store and the command exits (status 3)."""
    return "detach"


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP: the run is aborted like a second Ctrl-C (a KeyboardInterrupt, so that no
    ``except Exception`` on the way swallows it)."""


@contextmanager
def signals_control(engine: RunEngine) -> Iterator[None]:
    """Ctrl-C, SIGTERM and SIGHUP while ``engine`` runs (see the module docstring)."""
    presses = {"count": 0, "resumes": engine.resumes}
    aborting = {"now": False}

    def abort(reason: str, exception: type[KeyboardInterrupt]) -> None:
        aborting["now"] = True
        engine.request_abort(reason)
        if not engine.ending:  # an end already being recorded must not be cut short
            raise exception(reason)

    def on_sigint(signum, frame):
        if aborting["now"]:
            return  # the abort is being recorded; let it finish
        if engine.resumes != presses["resumes"]:  # the run came back from a pause: count afresh
            presses["count"], presses["resumes"] = 0, engine.resumes
        presses["count"] += 1
        if presses["count"] == 1:
            print("\nCtrl-C: pausing at the next safe point (Ctrl-C again aborts)", file=sys.stderr, flush=True)
            engine.request_pause("Ctrl-C")
        else:
            abort("aborted by a second Ctrl-C", KeyboardInterrupt)

    def on_terminate(signum, frame):
        if aborting["now"]:
            return
        abort(f"aborted by {signal.Signals(signum).name}", Terminated)

    handled = [(signal.SIGINT, on_sigint), (signal.SIGTERM, on_terminate)]
    if hasattr(signal, "SIGHUP"):
        handled.append((signal.SIGHUP, on_terminate))
    previous = {sig: signal.signal(sig, handler) for sig, handler in handled}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def cell_directory(runs_dir: Path) -> Path:
    """A new folder for one simulated cell under ``<runs>/sim``: never shared, even by two cells
    started in the same second (frames and truth logs must not mix)."""
    parent = Path(runs_dir) / "sim"
    parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=time.strftime("%Y%m%d-%H%M%S-"), dir=parent))


@contextmanager
def station_for(station: str | None, runs_dir: Path, seed: int) -> Iterator[str | None]:
    """``sim`` starts the simulated cell for the run (its files kept in a folder of its own under the runs folder)."""
    if station != "sim":
        yield station
        return
    from sim_devices.cell import SimCell

    directory = cell_directory(runs_dir)
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
    """Execute with the display and the signal handling; print the outcome; return the exit code."""
    with signals_control(engine):
        state = engine.execute()
    run = engine.store.get_run(engine.run_id)
    if args.jsonl:
        print(json.dumps({"event": "done", "run_id": engine.run_id, "state": state, "reason": run["reason"]}))
    else:
        print(f"\nrun {engine.run_id}: {state}" + (f" — {run['reason']}" if run["reason"] else ""), file=sys.stderr)
        if args.quiet:
            print(f"{engine.run_id} {state}")
    return EXIT_CODES.get(state, 1)
