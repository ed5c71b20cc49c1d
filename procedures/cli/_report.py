"""``instrument report RUN [--pdf] [-o FILE]``: write the run's self-contained HTML report, or the PDF
rendered from the same HTML and its print stylesheet."""

from __future__ import annotations

from pathlib import Path

from procedures.cli._common import add_runs_dir, find_run, open_store, write_output
from procedures.station import RunError


def register(subparsers) -> None:
    parser = subparsers.add_parser("report", help="write a run's HTML report (or, with --pdf, its PDF)")
    parser.add_argument("run_id", metavar="RUN")
    parser.add_argument("--pdf", action="store_true",
                        help="write a PDF (A4, page headers and numbers) from the same content as the HTML")
    parser.add_argument("-o", "--output", default=None,
                        help="output file (default: RUNS/<run>/report.html, or report.pdf with --pdf)")
    add_runs_dir(parser)
    parser.set_defaults(handler=run)


def run(args) -> int:
    from procedures.report import render_report  # the measurement stack loads only when needed

    with open_store(args) as store:
        r = find_run(store, args.run_id)
        if r is None:
            return 1
        html = render_report(r, store.samples(r["id"]), store.events(r["id"]), store.superseded_samples(r["id"]))
        default = store.run_dir(r["id"]) / ("report.pdf" if args.pdf else "report.html")
        path = Path(args.output) if args.output else default
        if not args.output and store.read_only:
            raise RunError(f"store is read-only: {store.location}: the report cannot be written to {default}; "
                           "give a file elsewhere with -o FILE")
    if args.pdf:
        from procedures.report import render_pdf  # WeasyPrint and Pango load only for a PDF

        pdf = render_pdf(html)
        try:
            path.write_bytes(pdf)
        except OSError as exc:
            raise RunError(f"cannot write {path}: {exc.strerror or exc}") from None
    else:
        write_output(path, html)
    print(path)
    return 0
