"""``instrument report RUN``: write the run's self-contained HTML report."""

from __future__ import annotations

from pathlib import Path

from procedures._cli_common import add_runs_dir, find_run, open_store, write_output


def register(subparsers) -> None:
    parser = subparsers.add_parser("report", help="write a run's HTML report")
    parser.add_argument("run_id", metavar="RUN")
    parser.add_argument("-o", "--output", default=None, help="HTML file (default: RUNS/<run>/report.html)")
    add_runs_dir(parser)
    parser.set_defaults(handler=run)


def run(args) -> int:
    from procedures._report import render_report  # the measurement stack loads only when needed

    with open_store(args) as store:
        r = find_run(store, args.run_id)
        if r is None:
            return 1
        html = render_report(r, store.samples(r["id"]), store.events(r["id"]), store.superseded_samples(r["id"]))
        path = Path(args.output) if args.output else store.run_dir(r["id"]) / "report.html"
    write_output(path, html)
    print(path)
    return 0
