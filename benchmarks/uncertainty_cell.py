"""Benchmark: does the expanded uncertainty U of a real ISO 9283 run cover the truth on the simulated cell?

Run: OMP_NUM_THREADS=1 .venv/bin/python benchmarks/uncertainty_cell.py [--cells N] [--runs N] [--cycles N]
     [--grid quick|paper] [--draws N] [--seed N] [--time-scale S] [--json FILE]

For each of ``--cells`` simulated cells (seeds seed, seed + 1, ...: each its own world, screens,
robot and air), the displacement and the angle calibration run through the engine and the real
client libraries (``--grid quick``: 10 mm and 0.25° steps, 2 repeats; ``paper``: the demo's 5 mm,
0.25°, 3 repeats), then ``--runs`` short ISO 9283 runs (``--cycles`` cycles each) with both records
in force. Each run's analysis evaluates its figures' U from its own data (the budget the procedure
builds: docs/uncertainty.md, "Wiring it into a run"); the twins' truth gives the true figures.
Every run's figures then go through ``instrument.uncertainty.coverage_study`` (the same budget and
poses, ``--draws`` draws) and the table gives, per figure and per family, pooled over points and
runs: coverage = fraction of |value − true| ≤ U (target 93–98 %), tightness = median U / RMS error
(≈ 2 for a well-sized U). Without --json nothing is written but the table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import yaml

from instrument.uncertainty import CoverageTable, coverage_study
from procedures.engine import open_engine, resolve_procedure_path
from procedures.kinds.iso import coverage_case

FAMILIES = {
    "RP_l, RP_a/b/c": ("rp_l", "rp_a", "rp_b", "rp_c"),
    "AP_P, AP_x/y/z, AP_a/b/c": ("ap_p", "ap_x", "ap_y", "ap_z", "ap_a", "ap_b", "ap_c"),
    "drift dAP, dRP": ("dap_p", "dap_a", "dap_b", "dap_c", "drp_l", "drp_a", "drp_b", "drp_c"),
    "AD, RD (P2-P4)": ("ad_p", "ad_x", "ad_y", "ad_z", "ad_a", "ad_b", "ad_c", "rd_p", "rd_x", "rd_y", "rd_z",
                       "rd_a", "rd_b", "rd_c"),
}
GRIDS = {
    "quick": ({"step_mm": 10.0, "repeats": 2}, {"step_deg": 0.25, "repeats": 2}),
    "paper": ({}, {}),
}
FAST = {"settle_time_s": 0.05, "frames_per_pose": 1}


def write_procedure(name: str, directory: Path, overrides: dict[str, Any]) -> Path:
    data = yaml.safe_load(resolve_procedure_path(name).read_text(encoding="utf-8"))
    data["parameters"].update(overrides)
    path = directory / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def run(runs_dir: Path, procedure: Path, station: Path) -> dict[str, Any]:
    with open_engine(runs_dir, procedure=procedure, station=station) as engine:
        state = engine.execute()
        stored = engine.store.get_run(engine.run_id)
    if state != "FINISHED":
        raise SystemExit(f"{procedure.name}: {state}: {stored['reason']}")
    return stored


def cell_runs(seed: int, args: argparse.Namespace, directory: Path) -> list[dict[str, Any]]:
    """Calibrate one simulated cell, then the ISO runs; their results."""
    from sim_devices.cell import SimCell

    displacement_grid, angle_grid = GRIDS[args.grid]
    with SimCell(seed=seed, directory=directory / f"cell{seed}", time_scale=args.time_scale) as cell:
        started = time.monotonic()
        displacement = run(directory / "runs", write_procedure(
            "displacement_calibration", directory, {**FAST, "interferometer_average_s": 0.05, **displacement_grid}),
            cell.station_path)
        angle = run(directory / "runs", write_procedure(
            "angle_calibration", directory, {**FAST, "table_speed_deg_s": 20.0, **angle_grid}), cell.station_path)
        station = yaml.safe_load(cell.station_path.read_text(encoding="utf-8"))
        station["calibration"] = {"record": [displacement["results"]["record_path"], angle["results"]["record_path"]]}
        calibrated = directory / f"station-{seed}.yaml"
        calibrated.write_text(yaml.safe_dump(station, sort_keys=False), encoding="utf-8")
        print(f"cell {seed}: calibrated in {time.monotonic() - started:.0f} s", file=sys.stderr)
        iso = write_procedure("iso9283_repeatability", directory,
                              {**FAST, "cycles": args.cycles, "uncertainty_draws": args.draws})
        out = []
        for index in range(args.runs):
            started = time.monotonic()
            out.append({"results": run(directory / "runs", iso, calibrated)["results"],
                        "tool_in_opr": station["frames"]["tool_in_opr"]})
            print(f"cell {seed}: ISO run {index + 1}/{args.runs} in {time.monotonic() - started:.0f} s",
                  file=sys.stderr)
    return out


def family_lines(table: CoverageTable) -> list[str]:
    lines = [f"{'figures':<28} {'n':>6} {'pooled':>7} {'min':>6} {'max':>6} {'tightness':>10}"]
    for family, names in FAMILIES.items():
        rows = [r for r in table.rows if r.figure in names]
        if not rows:
            continue
        count = sum(r.count for r in rows)
        pooled = sum(r.coverage * r.count for r in rows) / count
        tightness = float(np.median([r.tightness for r in rows]))
        lines.append(f"{family:<28} {count:>6} {pooled:>7.3f} {min(r.coverage for r in rows):>6.3f} "
                     f"{max(r.coverage for r in rows):>6.3f} {tightness:>10.2f}")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=4, help="simulated cells, each calibrated (default 4)")
    parser.add_argument("--runs", type=int, default=5, help="ISO runs per cell (default 5)")
    parser.add_argument("--cycles", type=int, default=5, help="cycles per ISO run (default 5)")
    parser.add_argument("--grid", choices=sorted(GRIDS), default="quick", help="calibration grids (default quick)")
    parser.add_argument("--draws", type=int, default=300, help="Monte Carlo draws per run (default 300)")
    parser.add_argument("--seed", type=int, default=0, help="first cell's seed")
    parser.add_argument("--time-scale", type=float, default=4.0, help="simulated seconds per wall second")
    parser.add_argument("--squareness-urad", type=float, default=None,
                        help="also the coverage with this frame squareness stated (µrad; the runs state none)")
    parser.add_argument("--json", type=Path, default=None, help="also write the runs' results and the table here")
    args = parser.parse_args(argv)
    started = time.monotonic()
    results = []
    with tempfile.TemporaryDirectory(prefix="uncertainty-cell-") as scratch:
        for seed in range(args.seed, args.seed + args.cells):
            results += cell_runs(seed, args, Path(scratch))
    variants = [("the budget the runs built", None)]
    if args.squareness_urad is not None:
        variants.append((f"with a frame squareness of {args.squareness_urad:g} µrad stated",
                         args.squareness_urad * 1e-6))
    tables = {}
    for title, squareness in variants:
        cases = [case for case in (coverage_case(r["results"], r["tool_in_opr"], frame_squareness=squareness)
                                   for r in results) if case is not None]
        if not cases:
            raise SystemExit("no run had an evaluated uncertainty and truth")
        table = coverage_study(cases, draws=args.draws, seed=args.seed)
        tables[title] = table.to_dict()
        print(f"\n== {title}: {len(cases)} ISO runs of {args.cycles} cycles on {args.cells} simulated cells "
              f"({args.grid} calibration grids), {args.draws} draws; {time.monotonic() - started:.0f} s\n")
        print("\n".join(family_lines(table)))
        print()
        print(table.format())
        outside = table.outside_target()
        print(f"\noutside 93-98 %: {', '.join(outside) if outside else 'none'}")
    if args.json:
        args.json.write_text(json.dumps({"arguments": vars(args) | {"json": str(args.json)}, "tables": tables,
                                         "runs": results}, default=str), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
