"""``instrument runs``: the runs in the store, oldest first."""

from __future__ import annotations

import json
import time

from procedures._cli_common import add_runs_dir, open_store


def register(subparsers) -> None:
    parser = subparsers.add_parser("runs", help="list the runs in the run store")
    parser.add_argument("--json", action="store_true", help="one JSON object per run")
    add_runs_dir(parser)
    parser.set_defaults(handler=run)


def run(args) -> int:
    with open_store(args) as store:
        runs = store.list_runs()
    for r in runs:
        if args.json:
            print(json.dumps(r))
            continue
        created = time.strftime("%Y-%m-%d %H:%M", time.localtime(r["created"]))
        print(f"{r['id'][:12]}  {created}  {r['state']:<8}  {r['samples']:>5}/{r['total_steps'] or 0:<5}  "
              f"{r['procedure']:<25} {r['station_name'] or ''}" + (f"  ({r['reason']})" if r["reason"] else ""))
    if not runs and not args.json:
        print("no runs")
    return 0
