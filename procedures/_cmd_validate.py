"""``instrument validate FILE...``: check station and procedure files; every problem as file:line."""

from __future__ import annotations

import sys

from procedures._errors import ConfigError
from procedures._loading import detect_kind, load_procedure, load_station


def register(subparsers) -> None:
    parser = subparsers.add_parser("validate", help="check station and procedure YAML files")
    parser.add_argument("files", nargs="+", metavar="FILE")
    parser.set_defaults(handler=run)


def run(args) -> int:
    status = 0
    for name in args.files:
        try:
            kind = detect_kind(name)
            model = load_station(name) if kind == "station" else load_procedure(name)
        except ConfigError as exc:
            status = 1
            for problem in exc.problems:
                print(problem, file=sys.stderr)
            continue
        what = model.procedure if kind == "procedure" else "station"
        print(f"{name}: OK ({what})")
    return status
