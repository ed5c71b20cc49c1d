"""``instrument resume RUN``: continue a paused, failed or interrupted run from its last committed sample."""

from __future__ import annotations

import sys

from procedures.cli._common import (
    RUN_EXIT_CODES,
    add_display,
    add_runs_dir,
    add_seed,
    console_pause_handler,
    detach_at_once,
    drive,
    open_store,
    refuse_read_only,
    seconds_value,
    station_for,
)
from procedures.station import RunLocked


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "resume", help="continue an interrupted or paused run",
        description="Continue a paused, failed or interrupted run from its last committed sample: the steps "
                    "stored as measured are skipped, failed ones measured again.", epilog=RUN_EXIT_CODES)
    parser.add_argument("run_id", metavar="RUN", help="run id (a unique prefix is enough)")
    parser.add_argument("--station", default=None,
                        help="station YAML, or 'sim' for a new simulated cell (default: a run measured on a simulated "
                             "cell gets a new one; any other run its station snapshot)")
    add_seed(parser, None)
    parser.add_argument("--pause-timeout", type=seconds_value, default=3600.0,
                        help="seconds a paused run waits before it is left paused (non-interactive)")
    add_runs_dir(parser)
    add_display(parser)
    parser.set_defaults(handler=run)


def run(args) -> int:
    from procedures.cli._display import Display
    from procedures.engine import open_engine
    from procedures.kinds import KINDS

    with open_store(args) as store:
        refuse_read_only(args, store)
        try:
            stored = store.get_run(args.run_id)
        except KeyError as exc:
            print(exc.args[0], file=sys.stderr)
            return 1
        # Checked before a simulated cell is started for nothing; open_engine takes the lease for real.
        holder = store.lease_holder(stored["id"])
        if holder is not None:
            raise RunLocked(f"run {stored['id']} is already being run by pid {holder['pid']} on {holder['host']}; "
                            "wait for it to end or stop that process")
    simulation = (stored["station"] or {}).get("simulation") or {}
    station_arg = args.station
    if station_arg is None and simulation and not _cell_running(simulation):
        station_arg = "sim"  # its cell ended with the session that measured it: a new one, as --station sim
    seed = args.seed if args.seed is not None else _stored_seed(stored)
    session = _next_session(simulation) if station_arg == "sim" else 0
    mode = "jsonl" if args.jsonl else "quiet" if args.quiet else "bar"
    display = Display(mode)
    if station_arg == "sim" and args.station is None and not args.quiet and not args.jsonl:
        print(f"run {stored['id']} was measured on a simulated cell: starting a new one (seed {seed}, session "
              f"{session})", file=sys.stderr)
    kind = KINDS.get(stored["procedure"])
    motion_truth = kind is None or kind.measures_in_motion
    with station_for(station_arg, args.runs_dir, seed, session=session, motion_truth=motion_truth) as station:
        with open_engine(args.runs_dir, run_id=stored["id"], station=station, listener=display,
                         pause_handler=detach_at_once if args.jsonl else
                         lambda engine: console_pause_handler(engine, display),
                         pause_timeout_s=args.pause_timeout, store=args.store) as engine:
            return drive(engine, args, display)


def _cell_running(simulation: dict) -> bool:
    """Whether the simulated cell a run was measured on still runs (its control channel answers a ping)."""
    control = simulation.get("control") or {}
    if not isinstance(control.get("host"), str) or not isinstance(control.get("port"), int):
        return False
    from sim_devices.control import ControlClient, ControlError  # only for a run measured on a simulated cell

    try:
        return bool(ControlClient(control["host"], control["port"], timeout=2.0).call("ping") == "pong")
    except (ControlError, OSError, ValueError):
        return False


def _next_session(simulation: dict) -> int:
    """The session number of the next simulated cell of a run: one more than every cell it was measured on
    (each leaves its truth log in the snapshot), so the new cell's noise is its own."""
    recorded = simulation.get("session")
    cells = len(simulation.get("earlier_truth_logs") or []) + (1 if simulation.get("truth_log") else 0)
    return max(cells, recorded + 1 if isinstance(recorded, int) and recorded >= 0 else 0)


def _stored_seed(run: dict) -> int:
    """The simulated cell's seed in the run's station snapshot (0 if it has none usable)."""
    seed = ((run["station"] or {}).get("simulation") or {}).get("seed")
    return seed if isinstance(seed, int) and 0 <= seed < 2**32 else 0
