"""The ``instrument`` command line.

Each subcommand lives in its own module ``procedures/_cmd_<name>.py`` exposing
``register(subparsers)``; this file only assembles them.
"""

from __future__ import annotations

import argparse
import sys

from instrument import __version__
from procedures import (
    _cmd_export,
    _cmd_locate,
    _cmd_report,
    _cmd_resume,
    _cmd_run,
    _cmd_runs,
    _cmd_serve,
    _cmd_show,
    _cmd_sim,
    _cmd_validate,
)

COMMANDS = (_cmd_locate, _cmd_sim, _cmd_validate, _cmd_run, _cmd_resume, _cmd_runs, _cmd_show, _cmd_report,
            _cmd_export, _cmd_serve)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="instrument",
        description="Robot pose repeatability (ISO 9283) with a cross-laser optical pose reference.",
    )
    parser.add_argument("--version", action="version", version=f"instrument {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for command in COMMANDS:
        command.register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "handler", None):
        parser.print_help()
        return 2
    try:
        return int(args.handler(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
