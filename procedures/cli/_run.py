"""``instrument run PROCEDURE --station STATION``: dry run, then measure; everything to the run store."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import procedures
from procedures.cli._common import (
    RUN_EXIT_CODES,
    add_display,
    add_runs_dir,
    add_seed,
    console_pause_handler,
    detach_at_once,
    drive,
    refuse_read_only,
    seconds_value,
    station_for,
)


def built_in_names() -> list[str]:
    """The built-in procedures' names: the YAML files of the ``procedures`` folder, where the engine finds
    them too (``procedures.engine.PACKAGE_DIR``), listed without loading the engine."""
    return sorted(path.stem for path in Path(procedures.__file__).resolve().parent.glob("*.yaml"))


def register(subparsers) -> None:
    built_in = ", ".join(built_in_names())
    parser = subparsers.add_parser(
        "run", help="run a procedure on a station",
        description="Dry-run the procedure on the station, then measure; every sample is committed to the run "
                    "store before the next motion. Ctrl-C once pauses at the next safe point, twice aborts. At "
                    "the end: the key results and the report's path.",
        epilog=RUN_EXIT_CODES)
    parser.add_argument("procedure", metavar="PROCEDURE", help=f"procedure file, or a built-in name ({built_in})")
    parser.add_argument("--station", required=True, help="station YAML, or 'sim' to start the simulated cell")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="PARAMETER=VALUE",
                        help="change one procedure parameter for this run, validated like the file and stored "
                             "with the run (repeatable), e.g. --set cycles=5 --set settle_time_s=0.05")
    parser.add_argument("--calibration", action="append", default=[], metavar="FILE",
                        help="with --station sim: a calibration record to put in force (repeatable: displacement "
                             "and angle records)")
    add_seed(parser, 0)
    parser.add_argument("--pause-timeout", type=seconds_value, default=3600.0,
                        help="seconds a paused run waits before it is left paused (non-interactive)")
    add_runs_dir(parser)
    add_display(parser)
    parser.set_defaults(handler=run)


def check_procedure(name: str, overrides: list[str]) -> str:
    """The procedure (a file or a built-in name) and its ``--set`` overrides, validated as ``open_engine`` will:
    a ``ConfigError`` (one line per problem) before anything is started for the run. Returns its kind's name."""
    from procedures.engine import apply_overrides, load_procedure, resolve_procedure_path
    from procedures.station import ConfigError, InputRefused, read_text_file

    path = resolve_procedure_path(name)
    try:
        text = read_text_file(path, what="procedure file")
    except InputRefused as exc:
        raise ConfigError([str(exc)]) from None
    if overrides:
        procedure = apply_overrides(path, text, list(overrides))[1]
    else:
        procedure = load_procedure(path, text)
    return procedure.procedure


def run(args: argparse.Namespace) -> int:
    from procedures.cli._display import Display
    from procedures.engine import open_engine
    from procedures.kinds import KINDS

    kind = check_procedure(args.procedure, args.overrides)  # a typo or a bad --set must not start a simulated cell
    refuse_read_only(args)  # a store that cannot be written must not start a simulated cell either
    mode = "jsonl" if args.jsonl else "quiet" if args.quiet else "bar"
    display = Display(mode)
    with station_for(args.station, args.runs_dir, args.seed, args.calibration,
                     motion_truth=KINDS[kind].measures_in_motion) as station:
        with open_engine(args.runs_dir, procedure=args.procedure, station=station, listener=display,
                         pause_handler=detach_at_once if args.jsonl else
                         lambda engine: console_pause_handler(engine, display),
                         pause_timeout_s=args.pause_timeout, store=args.store, overrides=args.overrides) as engine:
            if mode == "bar":
                changed = f" with {' '.join('--set ' + item for item in args.overrides)}" if args.overrides else ""
                print(f"run {engine.run_id} ({engine.procedure.procedure}{changed}) in {engine.store.location}",
                      file=sys.stderr)
            return drive(engine, args, display)
