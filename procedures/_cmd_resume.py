"""``instrument resume RUN``: continue a paused, failed or interrupted run from its last committed sample."""

from __future__ import annotations

import sys

from procedures._cli_common import Display, add_display, add_runs_dir, console_pause_handler, drive, station_for
from procedures._errors import ConfigError, RunError


def register(subparsers) -> None:
    parser = subparsers.add_parser("resume", help="continue an interrupted or paused run")
    parser.add_argument("run_id", metavar="RUN", help="run id (a unique prefix is enough)")
    parser.add_argument("--station", default=None,
                        help="station YAML (default: the run's station snapshot), or 'sim' for a new simulated cell")
    parser.add_argument("--seed", type=int, default=None, help="simulated cell seed (default: the run's)")
    parser.add_argument("--pause-timeout", type=float, default=3600.0)
    add_runs_dir(parser)
    add_display(parser)
    parser.set_defaults(handler=run)


def run(args) -> int:
    from procedures._api import open_engine
    from procedures._store import RunStore

    with RunStore(args.runs_dir) as store:
        try:
            stored = store.get_run(args.run_id)
        except KeyError as exc:
            print(exc.args[0], file=sys.stderr)
            return 1
    seed = (
        args.seed
        if args.seed is not None
        else int(((stored["station"] or {}).get("simulation") or {}).get("seed") or 0)
    )
    mode = "jsonl" if args.jsonl else "quiet" if args.quiet else "bar"
    try:
        with station_for(args.station, args.runs_dir, seed) as station:
            with open_engine(args.runs_dir, run_id=stored["id"], station=station, listener=Display(mode),
                             pause_handler=None if args.jsonl else console_pause_handler,
                             pause_timeout_s=args.pause_timeout) as engine:
                return drive(engine, args)
    except (ConfigError, RunError) as exc:
        print(str(exc), file=sys.stderr)
        return 1
