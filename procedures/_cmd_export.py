"""``instrument export RUN --csv|--json``: the run's samples (CSV) or everything (JSON)."""

from __future__ import annotations

import sys

from procedures._cli_common import add_runs_dir, find_run, open_store, write_output


def register(subparsers) -> None:
    parser = subparsers.add_parser("export", help="export a run as CSV (samples) or JSON (run, samples, events)")
    parser.add_argument("run_id", metavar="RUN")
    fmt = parser.add_mutually_exclusive_group(required=True)
    fmt.add_argument("--csv", action="store_true")
    fmt.add_argument("--json", action="store_true")
    parser.add_argument("-o", "--output", default=None, help="file (default: stdout)")
    add_runs_dir(parser)
    parser.set_defaults(handler=run)


def run(args) -> int:
    from procedures._report import export_csv, export_json  # the measurement stack loads only when needed

    with open_store(args) as store:
        r = find_run(store, args.run_id)
        if r is None:
            return 1
        samples = store.samples(r["id"])
        text = export_csv(samples) if args.csv else export_json(r, samples, store.events(r["id"]),
                                                                store.superseded_samples(r["id"]))
    if args.output:
        write_output(args.output, text)
    else:
        sys.stdout.write(text)
    return 0
