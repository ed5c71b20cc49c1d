"""``make demo``: the full job on the simulated cell.

Starts the simulated cell, runs the displacement calibration, the angle calibration and the
ISO 9283 repeatability cycle (5 points × 30 cycles) with the two calibration records in force,
writes the HTML report, and prints the ISO table with the cell's ground truth beside the measured
figures.

Run it with ``make demo`` or ``python -m procedures.demo [--cycles N] [--quick]``. Ctrl-C pauses the run
under way at its next safe point, as ``instrument run`` does (on a terminal: [Enter] resume, [a] abort,
[q] leave it paused and end the demo, with the ``instrument resume`` command that continues it); a second
Ctrl-C aborts it.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from instrument import ARCSEC
from procedures.cli import Display, console_pause_handler, resume_command, signals_control
from procedures.engine import open_engine, resolve_procedure_path
from procedures.report import render_report
from procedures.store import RunState, RunStore

# The demo keeps the paper's calibration grids and cycle count; what it shortens are the waits
# that a real cell needs and a simulated one does not (settling, averaging, repeated frames).
DEMO_PARAMETERS: dict[str, dict[str, Any]] = {
    "displacement_calibration": {"settle_time_s": 0.05, "interferometer_average_s": 0.05, "frames_per_pose": 1,
                                 "speed_percent": 50, "acceleration_percent": 50},
    "angle_calibration": {"settle_time_s": 0.05, "frames_per_pose": 1, "table_speed_deg_s": 20.0},
    "iso9283_repeatability": {"settle_time_s": 0.05, "frames_per_pose": 1},
}
QUICK_PARAMETERS: dict[str, dict[str, Any]] = {
    "displacement_calibration": {"step_mm": 10.0, "repeats": 2},
    "angle_calibration": {"step_deg": 0.5, "repeats": 2},
}


def write_procedure(name: str, directory: Path, overrides: dict[str, Any]) -> Path:
    """A copy of the built-in procedure ``name`` with ``overrides`` applied to its parameters."""
    data = yaml.safe_load(resolve_procedure_path(name).read_text(encoding="utf-8"))
    data["parameters"].update(overrides)
    data["name"] = f"{data['name']} (demo)"
    path = directory / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


class DemoProgress:
    """Where the demo is (run k of n) and how long the runs after the current one will take: their
    planned poses and set-ups at the pace and set-up time seen so far, plus each finished run's own
    overhead (dry run, analysis), so the ETA covers the whole demo, set-up waits included."""

    def __init__(self, plans: list[tuple[int, int]]) -> None:
        self.plans = plans  # (steps, set-ups) per run, in order
        self.current = 0
        self.overheads: list[float] = []
        self.display: Display | None = None

    def later_s(self) -> float:
        event = self.display.last_progress if self.display is not None else {}
        pace, setup_s = event.get("pace_s") or 0.0, event.get("setup_s") or 0.0
        overhead = float(np.mean(self.overheads)) if self.overheads else 0.0
        return sum(steps * pace + setups * setup_s + overhead for steps, setups in self.plans[self.current + 1:])


def plan_sizes(procedures: list[Path], station: Path) -> list[tuple[int, int]]:
    """Planned poses and set-up changes of each procedure on the station (the plans are pure functions)."""
    from procedures.engine import load_procedure, load_station
    from procedures.kinds import kind_of

    model = load_station(station)
    sizes = []
    for path in procedures:
        procedure = load_procedure(path)
        plan = kind_of(procedure).plan(procedure.parameters, model)
        sizes.append((len(plan), sum(1 for a, b in zip(plan, plan[1:]) if a.setup != b.setup) + 1))
    return sizes


def run_procedure(runs_dir: Path, procedure: Path, station: Path, quiet: bool,
                  progress: DemoProgress | None = None) -> dict[str, Any]:
    started = time.monotonic()
    phase = (progress.current + 1, len(progress.plans)) if progress is not None else None
    display = Display("quiet" if quiet else "bar", phase=phase,
                      later_s=progress.later_s if progress is not None else None)
    if progress is not None:
        progress.display = display
    with open_engine(runs_dir, procedure=procedure, station=station, listener=display,
                     pause_handler=lambda engine: console_pause_handler(engine, display)) as engine:
        where = f"{phase[0]}/{phase[1]} " if phase else ""
        print(f"\n== {where}{engine.procedure.procedure}: run {engine.run_id}", file=sys.stderr, flush=True)
        with signals_control(engine), display:  # Ctrl-C pauses at the next safe point, a second one aborts
            state = engine.execute()
        run = engine.store.get_run(engine.run_id)
    elapsed = time.monotonic() - started
    print(f"   {state} in {elapsed:.0f} s" + (f" — {run['reason']}" if run["reason"] else ""), file=sys.stderr,
          flush=True)
    if state == RunState.PAUSED:
        command = resume_command(argparse.Namespace(runs_dir=runs_dir), run["id"])
        print(f"demo: {procedure.stem} left paused; continue it with: {command} (the demo's later runs were not "
              "started)", file=sys.stderr, flush=True)
        raise SystemExit(3)
    if state != RunState.FINISHED:
        raise SystemExit(f"demo: {procedure.name} ended {state}: {run['reason']}")
    if progress is not None:
        event = display.last_progress
        progress.overheads.append(max(elapsed - (event.get("pace_s") or 0.0) * event.get("total", 0)
                                      - (event.get("setup_s") or 0.0) * progress.plans[progress.current][1], 0.0))
        progress.current += 1
    return run


def iso_table(results: dict[str, Any]) -> str:
    """The paper's Table 1: RP per point, measured (± U, k = 2, where evaluated) beside the cell's ground truth."""
    header = ("| point | RP_l measured ± U (µm) [95 % CI] | RP_l true (µm) | RP_a meas. ± U / true (″) "
              "| RP_b meas. ± U / true (″) | RP_c meas. ± U / true (″) | AP_P measured (µm) |")
    lines = [header, "|" + " --- |" * 7]
    for point in results["order"]:
        entry = results["points"][point]
        m, t = entry["stats"], entry.get("true_stats") or {}
        figures = ((results.get("figures") or {}).get("points") or {}).get(point, {})

        def spread(key: str, scale: float, m=m, figures=figures) -> str:
            figure = figures.get(key) or {}
            if figure.get("expanded_uncertainty") is None:
                return f"{m[key] / scale:.2f}"
            return f"{figure['value'] / scale:.2f} ± {figure['expanded_uncertainty'] / scale:.2f}"

        def pair(key: str, t=t) -> str:
            true = f"{t[key] / ARCSEC:.2f}" if key in t else "–"
            return f"{spread(key, ARCSEC)} / {true}"

        interval = f" [{m['rp_l_ci'][0] * 1e6:.2f}, {m['rp_l_ci'][1] * 1e6:.2f}]" if m.get("rp_l_ci") else ""
        true_l = f"{t['rp_l'] * 1e6:.2f}" if "rp_l" in t else "–"
        lines.append(f"| {point} | {spread('rp_l', 1e-6)}{interval} | {true_l} | "
                     f"{pair('rp_a')} | {pair('rp_b')} | {pair('rp_c')} | {m['ap_p'] * 1e6:.1f} |")
    return "\n".join(lines)


def deviation_lines(results: dict[str, Any]) -> list[str]:
    """The run's deviations from ISO 9283 and the measurement system's warnings, one line each."""
    return [f"  {d['severity']}: {d['message']}" for d in results.get("deviations") or []]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m procedures.demo", description=__doc__.splitlines()[0])
    parser.add_argument("--runs-dir", type=Path, default=Path("runs"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cycles", type=int, default=30, help="ISO cycles (paper: 30)")
    parser.add_argument("--quick", action="store_true", help="coarser calibration grids (a smoke run)")
    parser.add_argument(
        "--quiet", action="store_true",
        help="no progress (by default: a live display on a terminal, a heartbeat line every 10 s elsewhere)")
    parser.add_argument("--time-scale", type=float, default=4.0,
                        help="simulated seconds per wall second for robot and table motion (default 4)")
    args = parser.parse_args(argv)
    if argv is None:  # Ctrl-C is the demo's even when started with SIGINT ignored (as `instrument`)
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return _demo(args)
    except KeyboardInterrupt:  # outside a run (the cell starting, between runs, the report): nothing to keep
        print("demo: interrupted", file=sys.stderr)
        return 130
    finally:
        if argv is None:  # the process is ours: its shutdown must not be cut short by another Ctrl-C
            signal.signal(signal.SIGINT, signal.SIG_IGN)


def _demo(args: argparse.Namespace) -> int:
    from sim_devices.cell import SimCell

    started = time.monotonic()
    cell_dir = args.runs_dir.resolve() / "sim" / time.strftime("demo-%Y%m%d-%H%M%S")
    with SimCell(seed=args.seed, directory=cell_dir, time_scale=args.time_scale) as cell:
        print(f"simulated cell up (seed {args.seed}); station file {cell.station_path}", file=sys.stderr)
        procedures = {}
        for name, overrides in DEMO_PARAMETERS.items():
            overrides = {**overrides, **(QUICK_PARAMETERS.get(name, {}) if args.quick else {})}
            if name == "iso9283_repeatability":
                overrides["cycles"] = args.cycles
            procedures[name] = write_procedure(name, cell_dir, overrides)

        progress = DemoProgress(plan_sizes(list(procedures.values()), cell.station_path))
        displacement = run_procedure(args.runs_dir, procedures["displacement_calibration"], cell.station_path,
                                     args.quiet, progress)
        angle = run_procedure(args.runs_dir, procedures["angle_calibration"], cell.station_path, args.quiet, progress)

        station = yaml.safe_load(cell.station_path.read_text(encoding="utf-8"))
        station["calibration"] = {"record": [displacement["results"]["record_path"], angle["results"]["record_path"]]}
        calibrated = cell_dir / "station-calibrated.yaml"
        calibrated.write_text(yaml.safe_dump(station, sort_keys=False), encoding="utf-8")
        iso = run_procedure(args.runs_dir, procedures["iso9283_repeatability"], calibrated, args.quiet, progress)

    with RunStore(args.runs_dir) as store:
        report_path = store.run_dir(iso["id"]) / "report.html"
        report_path.write_text(render_report(iso, store.samples(iso["id"]), store.events(iso["id"])),
                               encoding="utf-8")
    print("\nISO 9283 pose repeatability on the simulated cell (measured, compensated, ± U with k = 2; truth from "
          "the twins):")
    print(iso_table(iso["results"]))
    print("\ndeviations and warnings:")
    print("\n".join(deviation_lines(iso["results"])) or "  none")
    print(f"\ncalibration records: {displacement['results']['record_path']}\n"
          f"                     {angle['results']['record_path']}")
    print(f"report: {report_path}")
    print(f"demo finished in {time.monotonic() - started:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
