"""``instrument show RUN``: one run's provenance, progress, results summary and recent events."""

from __future__ import annotations

import json

from procedures.cli._common import READ_EXIT_CODES, add_runs_dir, find_run, open_store


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "show", help="show one run",
        description="One run: procedure, station, robot, state and reason, samples, software, calibration records, "
                    "its results summary and its recent events.", epilog=READ_EXIT_CODES)
    parser.add_argument("run_id", metavar="RUN", help="run id (a unique prefix is enough)")
    parser.add_argument("--json", action="store_true", help="the run row as JSON (with the number of samples)")
    add_runs_dir(parser)
    parser.set_defaults(handler=run)


def run(args) -> int:
    with open_store(args) as store:
        r = find_run(store, args.run_id)
        if r is None:
            return 1
        samples = store.samples(r["id"])
        events = store.events(r["id"])
    if args.json:
        print(json.dumps({**r, "samples": len(samples)}, indent=1, default=str))
        return 0
    from procedures.report import report_title, show_lines  # the measurement stack loads only for a run's results

    ok = sum(s.ok for s in samples)
    print(f"run        {r['id']}\ntitle      {report_title(r)}\n"
          f"procedure  {r['procedure']} ({r['procedure_name'] or ''})\n"
          f"station    {r['station_name']} ({r['station_path']})\nstate      {r['state']}"
          + (f" — {r['reason']}" if r["reason"] else "")
          + f"\nsamples    {ok} ok, {len(samples) - ok} failed, {r['total_steps']} planned\n"
          f"software   {r['software_version']}\ncalibration {r['calibration_record_id'] or 'none'}")
    if r.get("robot_serial"):
        print(f"robot      {r.get('robot_manufacturer') or ''} {r.get('robot_model') or ''} serial {r['robot_serial']}"
              f" (controller {r.get('robot_controller_version') or '?'})")
    for line in show_lines(r):
        print(line)
    print("recent events:")
    for e in events[-8:]:
        print(f"  {e['kind']}: {e['message']}")
    return 0
