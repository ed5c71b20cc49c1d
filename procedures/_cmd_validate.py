"""``instrument validate FILE...``: check station and procedure files; every problem as file:line."""

from __future__ import annotations

import sys

from procedures._errors import ConfigError


def register(subparsers) -> None:
    parser = subparsers.add_parser("validate", help="check station and procedure YAML files")
    parser.add_argument("files", nargs="+", metavar="FILE")
    parser.set_defaults(handler=run)


def run(args) -> int:
    from procedures._loading import detect_kind, load_procedure, load_station  # loads the measurement stack

    status = 0
    for name in args.files:
        try:
            if detect_kind(name) == "station":
                load_station(name)
                what = "station"
            else:
                what = load_procedure(name).procedure
        except ConfigError as exc:
            status = 1
            for problem in exc.problems:
                print(problem, file=sys.stderr)
            continue
        print(f"{name}: OK ({what})")
    return status
