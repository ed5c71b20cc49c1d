"""``instrument export RUN --csv|--json``: the run's samples (CSV) or everything (JSON).

The JSON holds the run row, its samples, the failed samples measured again later and its events (all
as stored), ``sessions`` (each session's test conditions, for runs stored since schema version 6), and
``results``: every figure as ``{value, expanded_uncertainty, coverage_factor, confidence_interval,
true, unit, budget}`` (SI), the test conditions and the deviations (docs/results.md).
"""

from __future__ import annotations

import json
import sys

from procedures.cli._common import add_runs_dir, find_run, open_store, write_output


def register(subparsers) -> None:
    parser = subparsers.add_parser("export", help="export a run as CSV (samples) or JSON (run, samples, events, "
                                                  "figures with their uncertainty, test conditions, deviations)")
    parser.add_argument("run_id", metavar="RUN")
    fmt = parser.add_mutually_exclusive_group(required=True)
    fmt.add_argument("--csv", action="store_true")
    fmt.add_argument("--json", action="store_true")
    parser.add_argument("-o", "--output", default=None, help="file (default: stdout)")
    parser.add_argument("--streams", action="store_true", help="with --json: the pose stream of every move measured "
                        "in motion (t, pose, raw, quality; SI), as \"streams\"")
    add_runs_dir(parser)
    parser.set_defaults(handler=run)


def run(args) -> int:
    from procedures.kinds import normalised_results
    from procedures.report import export_csv, export_json  # the measurement stack loads only when needed

    with open_store(args) as store:
        r = find_run(store, args.run_id)
        if r is None:
            return 1
        samples = store.samples(r["id"])
        if args.csv:
            text = export_csv(samples)
        else:
            document = json.loads(export_json(r, samples, store.events(r["id"]), store.superseded_samples(r["id"])))
            document["results"] = normalised_results(r)
            recorded = store.sessions(r["id"], earlier=False)
            if recorded:  # the run-level test conditions; runs stored before them carry theirs in their samples
                document["sessions"] = [session.to_stored() for session in recorded]
            if args.streams:
                from procedures.kinds import StreamRecord

                document["streams"] = [{"step": step, **StreamRecord.from_stored(stored).arrays(),
                                        "meta": stored.meta} for step, stored in store.streams(r["id"]).items()]
            text = json.dumps(document, indent=1, default=str) + "\n"
    if args.output:
        write_output(args.output, text)
    else:
        sys.stdout.write(text)
    return 0
