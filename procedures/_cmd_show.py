"""``instrument show RUN``: one run's provenance, progress, results summary and recent events."""

from __future__ import annotations

import json

import numpy as np

from procedures._cli_common import add_runs_dir, find_run, open_store


def register(subparsers) -> None:
    parser = subparsers.add_parser("show", help="show one run")
    parser.add_argument("run_id", metavar="RUN")
    parser.add_argument("--json", action="store_true", help="the run row as JSON")
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
    ok = sum(s.ok for s in samples)
    print(f"run        {r['id']}\nprocedure  {r['procedure']} ({r['procedure_name'] or ''})\n"
          f"station    {r['station_name']} ({r['station_path']})\nstate      {r['state']}"
          + (f" — {r['reason']}" if r["reason"] else "")
          + f"\nsamples    {ok} ok, {len(samples) - ok} failed, {r['total_steps']} planned\n"
          f"software   {r['software_version']}\ncalibration {r['calibration_record_id'] or 'none'}")
    results = r.get("results") or {}
    if results.get("kind") == "iso9283":
        print("point  n    RP_l (µm)  RP_a (°)   RP_b (°)   RP_c (°)   AP_P (µm)")
        for label in results["order"]:
            e = results["points"][label]
            s = e.get("stats")
            if s:
                print(f"{label:<5} {e['n']:>3}  {s['rp_l'] * 1e6:9.2f}  {np.degrees(s['rp_a']):9.5f}  "
                      f"{np.degrees(s['rp_b']):9.5f}  {np.degrees(s['rp_c']):9.5f}  {s['ap_p'] * 1e6:9.2f}")
    elif results.get("kind", "").endswith("_calibration"):
        print(f"record     {results['record_path']} ({results['record_id']})")
    print("recent events:")
    for e in events[-8:]:
        print(f"  {e['kind']}: {e['message']}")
    return 0
