"""``instrument run PROCEDURE --station STATION``: dry run, then measure; everything to the run store."""

from __future__ import annotations

import sys
from pathlib import Path

from procedures._cli_common import (
    Display,
    add_display,
    add_runs_dir,
    add_seed,
    console_pause_handler,
    detach_at_once,
    drive,
    seconds_value,
    station_for,
)


def register(subparsers) -> None:
    parser = subparsers.add_parser("run", help="run a procedure on a station")
    built_in = ", ".join(sorted(path.stem for path in Path(__file__).parent.glob("*.yaml")))
    parser.add_argument("procedure", metavar="PROCEDURE", help=f"procedure file, or a built-in name ({built_in})")
    parser.add_argument("--station", required=True, help="station YAML, or 'sim' to start the simulated cell")
    add_seed(parser, 0)
    parser.add_argument("--pause-timeout", type=seconds_value, default=3600.0,
                        help="seconds a paused run waits before it is left paused (non-interactive)")
    add_runs_dir(parser)
    add_display(parser)
    parser.set_defaults(handler=run)


def run(args) -> int:
    from procedures._api import open_engine

    mode = "jsonl" if args.jsonl else "quiet" if args.quiet else "bar"
    with station_for(args.station, args.runs_dir, args.seed) as station:
        with open_engine(args.runs_dir, procedure=args.procedure, station=station, listener=Display(mode),
                         pause_handler=detach_at_once if args.jsonl else console_pause_handler,
                         pause_timeout_s=args.pause_timeout) as engine:
            if not args.jsonl:
                print(f"run {engine.run_id} ({engine.procedure.procedure})", file=sys.stderr)
            return drive(engine, args)
