"""``instrument history --robot SERIAL``: one robot's RP and AP per point over time, changes flagged.

Every finished ISO 9283 run of the robot (the serial its controller reported at run start) in time
order, per point: RP_l, RP_a/b/c and AP_P with their uncertainty (the expanded uncertainty U when the
results carry it, else the half-width of the sampling interval; see ``procedures.report``). The runs
and figures are those of the kinds that declare ``history_figures``.
A figure is flagged when it moved from the robot's previous run by more than the two runs'
uncertainties combined, ``|Δ| > √(u₁² + u₂²)``: a change the measurement itself cannot explain.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from procedures.cli._common import READ_EXIT_CODES, add_runs_dir, open_store


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "history", help="one robot's RP/AP per point over time (by serial), changes beyond the uncertainty flagged",
        description="Every finished ISO 9283 run of one robot, oldest first, per point: RP_l, RP_a/b/c and AP_P "
                    "with their uncertainty, and a flag (!) where a figure moved from the previous run by more "
                    "than both runs' uncertainties combined. The robot is named by the serial number its "
                    "controller reported (instrument runs shows it).", epilog=READ_EXIT_CODES)
    parser.add_argument("--robot", required=True, metavar="SERIAL", help="the robot's serial number")
    parser.add_argument("--json", action="store_true", help="the history as one JSON document (SI units)")
    add_runs_dir(parser)
    parser.set_defaults(handler=run)


COMPENSATION_GROUPS = {
    "compensated": "compensated (calibration records in force)",
    "uncompensated": "uncompensated (no calibration record: the figures include the instrument's own errors)",
    "not recorded": "compensation not recorded (results stored before it was)",
}


def compensation_of(run: dict[str, Any]) -> tuple[str, list[str]]:
    """Whether a run's figures were compensated (``COMPENSATION_GROUPS``) and with which records."""
    records = (run.get("results") or {}).get("compensation")
    if not isinstance(records, list):
        return "not recorded", []
    return ("compensated" if records else "uncompensated"), [str(record) for record in records]


def robot_history(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The history of one robot's runs (whole rows, oldest first): per point, one entry per run, each saying
    whether its figures were compensated; a change is flagged against the previous run of the same kind
    (compensated against compensated), never across: the two differ by the instrument's systematic error."""
    from procedures.report import changes, history_figures, iso_rows

    points: dict[str, list[dict[str, Any]]] = {}
    keys = history_figures()
    for run in runs:
        group, records = compensation_of(run)
        for row in iso_rows(run.get("results") or {}, keys):
            entries = points.setdefault(row["point"], [])
            same = [entry for entry in entries if entry["compensation"] == group]
            previous = same[-1]["figures"] if same else None
            figures = {key: row[key] for key in keys}
            entries.append({"run_id": run["id"], "created": run["created"], "n": row["n"], "compensation": group,
                            "records": records, "figures": figures, "changed": changes(previous, figures)})
    identity = runs[-1] if runs else {}
    return {"serial": identity.get("robot_serial"), "manufacturer": identity.get("robot_manufacturer"),
            "model": identity.get("robot_model"), "runs": len(runs), "points": points}


def run(args: argparse.Namespace) -> int:
    from procedures.report import figure_columns, history_figures, history_procedures, shown  # on use

    with open_store(args) as store:
        runs = store.robot_runs(args.robot, procedures=history_procedures())
        known = [r["serial"] for r in store.robots()] if not runs else []
    if not runs:  # an unknown serial is a wrong input: one line, exit 1 (a robot with no ISO run yet too)
        others = f" (robots in the store: {', '.join(known)})" if known else " (no run in the store records a robot)"
        print(f"no finished ISO 9283 run of robot {args.robot}{others}", file=sys.stderr)
        return 1
    history = robot_history(runs)
    if args.json:
        print(json.dumps(history))
        return 0
    print(f"{history['manufacturer'] or ''} {history['model'] or ''} serial {history['serial']}: "
          f"{len(runs)} finished ISO 9283 runs".strip())
    flagged = 0
    columns = figure_columns(history_figures())
    groups = [(point, group, [e for e in entries if e["compensation"] == group])
              for point, entries in history["points"].items() for group in COMPENSATION_GROUPS]
    for point, group, entries in groups:
        if not entries:
            continue
        print(f"\n{point} — {COMPENSATION_GROUPS[group]}")
        table = [["date", "run", "n", *[f"{name} ({unit})" for _, name, unit, _ in columns], ""]]
        for entry in entries:
            changed = entry["changed"]
            flagged += bool(changed)
            table.append([time.strftime("%Y-%m-%d %H:%M", time.localtime(entry["created"])), entry["run_id"][:8],
                          str(entry["n"]), *[shown(entry["figures"][key], scale) + (" !" if key in changed else "")
                                             for key, _, _, scale in columns],
                          _changed_text(changed)])
        widths = [max(len(row[i]) for row in table) for i in range(len(table[0]))]
        for row in table:
            print("  ".join(cell.ljust(w) if i < 2 or i == len(row) - 1 else cell.rjust(w)
                            for i, (cell, w) in enumerate(zip(row, widths))).rstrip())
    print("\n± : expanded uncertainty U (k = 2), or the half-width of the 95 % interval where a run has no U; "
          "! : moved from the previous run of the same kind (compensated or not) by more than both uncertainties "
          "combined")
    if flagged:
        print(f"{flagged} point-runs changed beyond their uncertainty")
    return 0


def _changed_text(changed: dict[str, float]) -> str:
    from procedures.report import figure_columns, history_figures

    parts = []
    for key, name, unit, scale in figure_columns(history_figures()):
        if key in changed:
            parts.append(f"{name} {changed[key] * scale:+.2f} {unit}")
    return ("changed: " + ", ".join(parts)) if parts else ""
