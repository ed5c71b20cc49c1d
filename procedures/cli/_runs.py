"""``instrument runs``: the runs in the run store as an aligned table, oldest first, with filters."""

from __future__ import annotations

import argparse
import json
import shutil
import time

from procedures.cli._common import READ_EXIT_CODES, add_runs_dir, open_store
from procedures.store import RunState

REASON_CHARS = 60


def positive_int(text: str) -> int:
    """An argparse type: a whole number ≥ 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text[:20]!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected 1 or more, got {value}")
    return value


def state_value(text: str) -> RunState:
    """An argparse type: a run state, in any case."""
    try:
        return RunState(text.upper())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected one of {', '.join(s.value for s in RunState)}, "
                                         f"got {text[:20]!r}") from None


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "runs", help="list the runs in the run store",
        description="The runs in the store, oldest first: id, created, state, samples/planned, procedure, "
                    "station, robot and, for a run that did not finish, the first line of its reason.",
        epilog=READ_EXIT_CODES)
    parser.add_argument("--last", type=positive_int, default=None, metavar="N", help="only the newest N runs")
    parser.add_argument("--state", type=state_value, action="append", default=[], metavar="STATE",
                        help="only runs in this state (QUEUED, RUNNING, PAUSED, FINISHED, FAILED, ABORTED; "
                             "repeatable)")
    parser.add_argument("--procedure", default=None, metavar="NAME",
                        help="only runs of this procedure (e.g. iso9283_repeatability)")
    parser.add_argument("--robot", default=None, metavar="SERIAL", help="only runs on the robot with this serial")
    parser.add_argument("--json", action="store_true", help="one JSON object per run instead of the table")
    add_runs_dir(parser)
    parser.set_defaults(handler=run)


def one_line(text: str | None, width: int = REASON_CHARS) -> str:
    """The first line of ``text``, cut to ``width`` characters with an ellipsis."""
    first = (str(text or "").strip().splitlines() or [""])[0]
    return first if len(first) <= width else first[: width - 1] + "…"


def run(args: argparse.Namespace) -> int:
    with open_store(args) as store:
        runs = store.list_runs(states=args.state, procedure=args.procedure, robot=args.robot, last=args.last)
    if args.json:
        for r in runs:
            print(json.dumps(r))
        return 0
    if not runs:
        print("no runs" + (" match" if args.state or args.procedure or args.robot else ""))
        return 0
    header = ["RUN", "CREATED", "STATE", "SAMPLES", "PROCEDURE", "STATION", "ROBOT", "REASON"]
    rows = [[r["id"][:12], time.strftime("%Y-%m-%d %H:%M", time.localtime(r["created"])), str(r["state"]),
             f"{r['samples']}/{r['total_steps'] or 0}", r["procedure"], r["station_name"] or "",
             r["robot_serial"] or "", "" if r["state"] == RunState.FINISHED else one_line(r["reason"])]
            for r in runs]
    if not any(row[-1] for row in rows):
        header, rows = header[:-1], [row[:-1] for row in rows]
    if not any(row[6] for row in rows):
        header, rows = header[:6] + header[7:], [row[:6] + row[7:] for row in rows]
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header))]
    limit = shutil.get_terminal_size((200, 24)).columns
    for row in [header, *rows]:
        line = "  ".join(cell.rjust(width) if name == "SAMPLES" else cell.ljust(width)
                         for cell, width, name in zip(row, widths, header)).rstrip()
        print(line if len(line) <= limit else line[: limit - 1] + "…")
    return 0
