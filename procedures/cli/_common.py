"""Shared pieces of the run-related subcommands: the runs folder and store, the pause prompt, signals,
and the end of a run (its key results, its report, the one line of ``--quiet``, the ``done`` event).
The progress display is ``procedures.cli._display``; the results' lines ``procedures.report._summaries``.

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
from typing import TYPE_CHECKING, Any, TextIO

from procedures.station import RunError
from procedures.store import SQLITE_FILE, STORE_ENV, RunState, RunStore, StoreReadOnly, store_location

if TYPE_CHECKING:  # only for annotations: the engine's, the report's and the display's stacks load on use
    from procedures.cli._display import Display
    from procedures.engine import PauseDecision, RunEngine

__all__ = ["EXIT_CODES", "add_display", "add_runs_dir", "console_pause_handler", "detach_at_once",
           "drive", "open_store", "signals_control", "station_for"]

EXIT_CODES = {RunState.FINISHED: 0, RunState.FAILED: 1, RunState.ABORTED: 2, RunState.PAUSED: 3}
RUN_EXIT_CODES = ("exit codes: 0 finished, 1 failed or bad input (one line on stderr), 2 aborted (a second "
                  "Ctrl-C, SIGTERM, SIGHUP), 3 left paused (continue with: instrument resume RUN), "
                  "130 interrupted before the run started")
READ_EXIT_CODES = "exit codes: 0 done, 1 bad input, no such run or no store (one line on stderr), 2 bad arguments"


def add_runs_dir(parser) -> None:
    parser.add_argument("--runs-dir", default=os.environ.get("INSTRUMENT_RUNS", "runs"),
                        help="runs folder: per-run files and, by default, the store runs.sqlite "
                             "(default: $INSTRUMENT_RUNS or ./runs)")
    parser.add_argument("--store", default=None, metavar="URL",
                        help=f"a shared run store, postgresql://USER@HOST/DATABASE (default: ${STORE_ENV}, "
                             "else the runs folder's runs.sqlite); per-run files stay in the runs folder")


def add_display(parser) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--quiet", action="store_true",
                       help="print exactly one line at the end: RUN_ID STATE")
    group.add_argument("--jsonl", action="store_true",
                       help="one JSON event per line on stdout (for automation); the last is 'done' with the "
                            "state, reason, key results and report path")


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
    """The store a reading command uses (``--store``/``$INSTRUMENT_STORE``, else the runs folder's SQLite)."""
    path = Path(args.runs_dir)
    url = store_location(getattr(args, "store", None))
    if url is None and not (path / SQLITE_FILE).is_file():
        raise RunError(f"no run store in {path} (use --runs-dir or $INSTRUMENT_RUNS, or --store URL)")
    return RunStore(path, url=url)


def refuse_read_only(args, store: RunStore | None = None) -> None:
    """A writing command on a store that can only be read (or that another process holds locked): its one
    line, before anything is started."""
    if store is not None:
        if store.read_only:
            raise StoreReadOnly(f"store is read-only: {store.location} (this command writes to it; runs, show, "
                                "report -o FILE, export and history work)")
        store.check_writable()  # another process's lock: said now, not after a simulated cell has started
        return
    if store_location(getattr(args, "store", None)) is None:
        with RunStore(Path(args.runs_dir)) as opened:
            refuse_read_only(args, opened)


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


_ANSWERS: dict[str, PauseDecision] = {"\r": "resume", "\n": "resume", "a": "abort", "q": "detach"}
PAUSE_PROMPT = "run paused: [Enter] resume, [a] abort, [q] quit and leave it paused (instrument resume RUN) "


def ask_pause_key(fd: int, out: TextIO) -> PauseDecision:
    """Read single keys from terminal ``fd`` until one is an answer (no Enter needed after a or q).

    An unknown key asks again; end of input leaves the run paused. The terminal's own mode is put
    back whatever happens (a Ctrl-C meanwhile still aborts: signals stay on in cbreak mode).
    """
    import termios
    import tty

    saved = termios.tcgetattr(fd)
    try:
        tty.setcbreak(fd)
        print(f"\n{PAUSE_PROMPT}", end="", file=out, flush=True)
        while True:
            key = os.read(fd, 1).decode("utf-8", "replace")
            if not key:
                print("(no more input: left paused)", file=out, flush=True)
                return "detach"
            answer = _ANSWERS.get(key.lower())
            if answer is not None:
                print({"resume": "resuming", "abort": "aborting", "detach": "leaving it paused"}[answer],
                      file=out, flush=True)
                return answer
            shown = repr(key) if not key.isprintable() else key
            print(f"\n{shown}: not an answer. {PAUSE_PROMPT}", end="", file=out, flush=True)
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)


def console_pause_handler(engine: RunEngine, display: Display | None = None) -> PauseDecision:
    """Ask the operator what to do with a paused run (without a terminal: leave it paused)."""
    if not sys.stdin.isatty():
        return "detach"
    if display is not None:
        display.stop()  # the live display would draw over the prompt
    try:
        return ask_pause_key(sys.stdin.fileno(), sys.stderr)
    finally:
        if display is not None:
            display.start()


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


def calibration_files(paths: list[str]) -> list[str]:
    """``--calibration FILE`` values as absolute paths; a file that is not there is one line."""
    found = []
    for name in paths:
        path = Path(name)
        if not path.is_file():
            raise RunError(f"--calibration {name}: no such file (a calibration record, "
                           "runs/<run>/calibration-<kind>.json)")
        found.append(str(path.resolve()))
    return found


@contextmanager
def station_for(station: str | None, runs_dir: Path, seed: int, calibration: list[str] | None = None,
                session: int = 0, motion_truth: bool = True) -> Iterator[str | None]:
    """``sim`` starts the simulated cell for the run (its files kept in a folder of its own under the runs
    folder); ``calibration``: the records the cell's station puts in force (``--calibration``);
    ``session``: which start of a cell this is for the run (a resumed run's cell draws fresh noise);
    ``motion_truth``: whether the robot twin records its dense truth (the kind ``measures_in_motion``;
    sampling it is most of the twin's CPU, and a run measuring at rest never reads it)."""
    records = calibration_files(calibration or [])
    if records and station != "sim":
        raise RunError("--calibration goes with --station sim; a station file names its records in "
                       "calibration.record")
    if station != "sim":
        yield station
        return
    from sim_devices.cell import STATIC_ROBOT, SimCell

    directory = cell_directory(runs_dir)
    cell = SimCell(seed=seed, directory=directory, session=session,
                   config=None if motion_truth else {"robot": STATIC_ROBOT})
    try:
        cell.start()
    except KeyboardInterrupt:  # Ctrl-C while the twins start: none is left behind
        cell.stop()
        raise
    except Exception as exc:  # the twins' own message, without their traceback
        cell.stop()
        raise RunError(f"the simulated cell did not start: {str(exc).strip().splitlines()[-1]}") from None
    try:
        yield str(_with_records(Path(cell.station_path), records) if records else cell.station_path)
    finally:
        cell.stop()


def _with_records(station_path: Path, records: list[str]) -> Path:
    """A copy of the simulated cell's station file with ``records`` as its calibration records."""
    import yaml

    station = yaml.safe_load(station_path.read_text(encoding="utf-8"))
    station["calibration"] = {**(station.get("calibration") or {}), "record": records}
    path = station_path.with_name("station-calibrated.yaml")
    path.write_text(yaml.safe_dump(station, sort_keys=False), encoding="utf-8")
    return path


def drive(engine: RunEngine, args: argparse.Namespace, display: Display | None = None) -> int:
    """Execute with the display and the signal handling; print the outcome; return the exit code.

    At the end: the run's key results (``procedures.report._summaries``) and its report (written to
    ``<runs>/<run>/report.html``) on stdout, or ``--quiet``'s one line, or ``--jsonl``'s ``done`` event
    (with ``resume``, the command that continues a paused run); a paused run's last line is that command.
    """
    started = time.monotonic()
    with signals_control(engine):
        if display is not None:
            with display:
                state = engine.execute()
        else:
            state = engine.execute()
        # The run's end is stored: a Ctrl-C now would only cut its report and its last lines short.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        return _ended(engine, args, state, started)


def resume_command(args: argparse.Namespace, run_id: str) -> str:
    """The command that continues run ``run_id``, with the runs folder and store this command used."""
    command = f"instrument resume {run_id}"
    runs_dir = getattr(args, "runs_dir", None)
    if runs_dir is not None and str(runs_dir) != os.environ.get("INSTRUMENT_RUNS", "runs"):
        command += f" --runs-dir {runs_dir}"
    if getattr(args, "store", None):
        command += " --store URL"  # never the URL itself: it may carry a password
    return command


def _ended(engine: RunEngine, args: argparse.Namespace, state: RunState, started: float) -> int:
    from procedures.report import result_lines, result_summary

    run = engine.store.get_run(engine.run_id)
    report, report_problem = write_report(engine.store, run)
    reason = (str(run["reason"]).splitlines() or [""])[0] if run["reason"] else None
    if args.jsonl:
        print(json.dumps({"event": "done", "run_id": engine.run_id, "state": state, "reason": run["reason"],
                          "results": result_summary(run), "report": report,
                          "resume": resume_command(args, engine.run_id) if state == RunState.PAUSED else None},
                         default=str))
    elif args.quiet:
        print(f"{engine.run_id} {state}")  # scripts read these two words: nothing else, ever
    else:
        print(f"run {engine.run_id}: {state} after {_elapsed(time.monotonic() - started)}"
              + (f" — {reason}" if reason else ""))
        for line in result_lines(run):
            print(line)
        if report:
            print(f"report: {report}")
        elif report_problem:
            print(f"report: not written ({report_problem})", file=sys.stderr)
        if state == RunState.PAUSED:
            print(f"left paused; continue with: {resume_command(args, engine.run_id)}")
    return EXIT_CODES.get(state, 1)


def _elapsed(seconds: float) -> str:
    seconds = int(seconds)
    return f"{seconds // 60} min {seconds % 60:02d} s" if seconds >= 60 else f"{seconds} s"


def write_report(store: RunStore, run: dict[str, Any]) -> tuple[str | None, str | None]:
    """Write the run's HTML report to ``<runs>/<run>/report.html``; (its path, None) or (None, why not)."""
    from procedures.report import render_report  # the report stack loads only here

    try:
        html = render_report(run, store.samples(run["id"]), store.events(run["id"]),
                             store.superseded_samples(run["id"]))
        path = store.run_dir(run["id"]) / "report.html"
        path.write_text(html, encoding="utf-8")
    except OSError as exc:
        return None, f"cannot write it: {exc.strerror or exc}"
    except Exception as exc:  # a report must never turn a measured run into an error
        return None, f"{type(exc).__name__}: {(str(exc).splitlines() or [''])[0]}"
    return str(path), None
