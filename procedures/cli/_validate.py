"""``instrument validate FILE...``: check station and procedure files; every problem as file:line.

Given a station and procedures (``instrument validate STATION PROCEDURE...``), each procedure is
also dry-run on the station offline, as ``instrument run`` would before the first motion but
without the devices: its plan's size, every target inside the envelope and within the speed caps,
every cross on its screen, and the calibration records the station names readable. A problem that
repeats over many steps is printed once with the count of the others.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from procedures.station import ConfigError


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "validate", help="check station and procedure YAML files (with a station and procedures: also the offline "
                         "dry run of each procedure)",
        description="Check station and procedure files; every problem is one line FILE:LINE: FIELD: what was "
                    "expected. Given one station and procedures, each procedure is also dry-run on the station "
                    "offline (plan size, envelope, speed caps, crosses on their screens, calibration records).",
        epilog="exit codes: 0 every file valid (and every dry run clean), 1 a problem (one line each), "
               "2 bad arguments")
    parser.add_argument("files", nargs="+", metavar="FILE",
                        help="station and procedure YAML files (a procedure may also be a built-in name)")
    parser.set_defaults(handler=run)


def run(args) -> int:
    from procedures.engine import detect_kind, load_procedure, load_station

    status = 0
    stations, procedures = [], []
    for name in args.files:
        try:
            path = _resolved(name)
            if detect_kind(path) == "station":
                station = load_station(path)
                stations.append((name, station))
                record_problems = _record_problems(station)
                if record_problems:
                    raise ConfigError([f"{name}: {problem}" for problem in record_problems])
                what = "station"
            else:
                procedure = load_procedure(path)
                procedures.append((name, procedure))
                what = procedure.procedure
        except ConfigError as exc:
            status = 1
            for problem in exc.problems:
                print(problem, file=sys.stderr)
            continue
        print(f"{name}: OK ({what})")
    if len(stations) == 1:
        station_name, station = stations[0]
        for name, procedure in procedures:
            problems, steps = _dry_run(station, procedure)
            for problem in problems:
                print(f"{name}: dry run on {station_name}: {problem}", file=sys.stderr)
            if problems:
                status = 1
            else:
                print(f"{name}: dry run on {station_name}: OK ({steps} steps)")
    elif len(stations) > 1 and procedures:
        print("several stations given: the procedures are not dry-run (give one station)", file=sys.stderr)
    return status


def _resolved(name: str) -> str:
    """A file as named, or the built-in procedure of that name (``instrument run`` resolves it alike). A bare
    name that is neither is refused as ``run`` refuses it (with the nearest built-in); a path stays as given,
    for the reader to say why it cannot be read."""
    from procedures.engine import resolve_procedure_path

    if Path(name).exists():
        return name
    try:
        return str(resolve_procedure_path(name))
    except ConfigError:
        if Path(name).suffix or "/" in name or os.sep in name:
            return name
        raise


def _record_problems(station) -> list[str]:
    from procedures.engine import collapse, record_paths, record_problems
    from procedures.station import InstrumentScience

    return collapse(record_problems(record_paths(station), InstrumentScience()))


def _dry_run(station, procedure) -> tuple[list[str], int]:
    import numpy as np

    from drivers.robot import MotionEnvelope
    from procedures.engine import collapse, offline_problems
    from procedures.kinds import kind_of
    from procedures.station import InstrumentScience

    science = InstrumentScience()
    science.configure(station)
    plan = kind_of(procedure).plan(procedure.parameters, station)
    envelope = MotionEnvelope.from_dict(station.envelope.model_dump())
    problems = offline_problems(plan, envelope, np.asarray(station.frames.reference_tcp_pose, dtype=float),
                                science, procedure.parameters)
    return collapse(problems), len(plan)
