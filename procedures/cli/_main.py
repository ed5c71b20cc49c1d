"""The ``instrument`` command line: the parser and ``main``.

Each subcommand lives in its own module ``procedures/cli/_<name>.py`` exposing
``register(subparsers)``; this file only assembles them.

No command prints a traceback: a problem with the input or the run is one line on stderr (exit
status 1); an unforeseen error is one line naming the file that holds its traceback
(``<runs folder>/instrument-errors.log``; inside a run, the run's own log has it too). What the
client libraries log (python-can logs a lost connection with its traceback) goes to that file
too, not to the terminal. A reader that goes away (``instrument runs --json | head``) ends the
output quietly.
"""

from __future__ import annotations

import argparse
import datetime
import logging
import os
import sys
import tempfile
import traceback
from pathlib import Path

from instrument import __version__
from procedures.cli import (
    _export,
    _history,
    _interrupt_in_disguise,
    _locate,
    _report,
    _resume,
    _run,
    _runs,
    _serve,
    _show,
    _sim,
    _validate,
)
from procedures.station import ConfigError, InputRefused, RunError

COMMANDS = (_locate, _sim, _validate, _run, _resume, _runs, _show, _history, _report, _export, _serve)
EXIT_CODES_HELP = """exit codes:
  0    done (run/resume: the run FINISHED)
  1    failed: bad input, no such run or store, or the run FAILED (one line on stderr, never a traceback)
  2    run/resume: the run was ABORTED (second Ctrl-C, SIGTERM, SIGHUP); any command: bad arguments (usage)
  3    run/resume: the run was left PAUSED (continue it with: instrument resume RUN)
  130  interrupted before a run started

environment: INSTRUMENT_RUNS (runs folder, default ./runs), INSTRUMENT_STORE (postgresql:// URL of a shared
run store; default: the runs folder's runs.sqlite)"""
ERROR_LOG = "instrument-errors.log"
COMMON_HELP = {
    "run_id": "run id (a unique prefix is enough)",
    "csv": "one CSV row per sample (SI columns, the unit in each name)",
    "json": "the run, its samples, superseded samples and events as one JSON document",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="instrument",
        description="Robot pose repeatability (ISO 9283) with a cross-laser optical pose reference.",
        epilog=EXIT_CODES_HELP, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"instrument {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for command in COMMANDS:
        command.register(subparsers)
    for sub in subparsers.choices.values():  # arguments a command left without a help text get the common one
        for action in sub._actions:
            if action.help is None and action.dest in COMMON_HELP:
                action.help = COMMON_HELP[action.dest]
        if sub.epilog is None:
            sub.epilog = "exit codes: 0 done, 1 bad input or no such run (one line on stderr), 2 bad arguments"
    return parser


def _error_log(args: argparse.Namespace | None) -> Path:
    """The error log: in the runs folder if there is one, else in the temporary folder."""
    runs_dir = Path(getattr(args, "runs_dir", None) or os.environ.get("INSTRUMENT_RUNS", "runs"))
    folder = runs_dir if runs_dir.is_dir() and os.access(runs_dir, os.W_OK) else Path(tempfile.gettempdir())
    return folder / ERROR_LOG


def _log_traceback(args: argparse.Namespace | None) -> str:
    """Append the current exception's traceback to the error log; returns where it went."""
    path = _error_log(args)
    text = f"--- {datetime.datetime.now().isoformat(timespec='seconds')} instrument {' '.join(sys.argv[1:])}\n" \
           f"{traceback.format_exc()}\n"
    try:
        with open(path, "a", encoding="utf-8") as handle:
            handle.write(text)
    except OSError:
        return "nowhere (the error log could not be written)"
    return str(path)


class _LibraryLog(logging.Handler):
    """Client libraries' warnings and errors, appended to the error log (opened per record: the
    runs folder may appear only once the command has started)."""

    def __init__(self, args: argparse.Namespace) -> None:
        super().__init__(logging.WARNING)
        self.args = args
        self.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        try:
            with open(_error_log(self.args), "a", encoding="utf-8") as handle:
                handle.write(self.format(record) + "\n")
        except Exception:
            pass  # logging must never stop a measurement


def _quiet_stdout() -> None:
    """The reader of our stdout left: point stdout at /dev/null so that the interpreter's final
    flush does not complain either."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "handler", None):
        parser.print_help()
        return 2
    library_log = _LibraryLog(args)
    logging.getLogger().addHandler(library_log)  # instead of Python's last-resort print to stderr
    try:
        return _handled(args)
    finally:
        logging.getLogger().removeHandler(library_log)


def _handled(args: argparse.Namespace) -> int:
    try:
        return int(args.handler(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        _quiet_stdout()
        return 0
    except (ConfigError, RunError, InputRefused) as exc:
        print(str(exc), file=sys.stderr)
        return 1
    except MemoryError:
        print("instrument: out of memory", file=sys.stderr)
        return 1
    except Exception as exc:  # a bug: one line for the user, the traceback in the log
        if _interrupt_in_disguise(exc):
            print("interrupted", file=sys.stderr)
            return 130
        where = _log_traceback(args)
        first = (str(exc).splitlines() or [""])[0][:300]
        print(f"instrument: internal error: {type(exc).__name__}: {first} (traceback in {where})", file=sys.stderr)
        return 1
