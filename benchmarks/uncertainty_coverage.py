"""Benchmark: coverage and tightness of the expanded uncertainty U (k = 2) on synthetic ISO runs.

Run: OMP_NUM_THREADS=1 .venv/bin/python benchmarks/uncertainty_coverage.py [--runs N] [--draws N] [--seed N]

For each scenario, many seeded synthetic ISO 9283 runs with known truth (instrument.uncertainty.
synthetic_iso_run: robot scatter, frame noise, compensation residual, reference scale and noise,
transform and environment offsets; the budget estimated from each run's own data) go through
iso_uncertainty, and the table gives per figure, pooled over the five points and the runs:
coverage = fraction of |value − true| ≤ U (target 93–98 %), tightness = median U / RMS error
(≈ 2 for a well-sized U), mean and RMS error, median U; right of the bar the same with the noise
bias carried in U instead of corrected. Then the wall time of one full evaluation (1000 draws,
per-term contributions) of a 30-cycle run, as the procedures would call it.
Scenarios: n = 30 and n = 5 with the noise taken from the calibration's noise floor (one frame
per pose, as in the simulated cell); n = 10 with two independent frames per pose; n = 30 with
heavy-tailed (Student-t, 5 dof) frame noise that the budget treats as normal.
Last, a calibration's residual: 300 synthetic held-out sets (13 points × 9 observations, true
residual 0.5 µm RMS, reference noise 0.5 µm, scale 1 ppm) through calibration_residual_uncertainty,
coverage of U against the RMS of corrected − truth and the mean error before/after the bias step.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from instrument.uncertainty import (
    CoverageCase,
    SyntheticCell,
    calibration_residual_uncertainty,
    coverage_study,
    iso_uncertainty,
    synthetic_iso_run,
)

FAMILIES = {
    "RP_l, RP_a/b/c": ("rp_l", "rp_a", "rp_b", "rp_c"),
    "AP_P, AP_x/y/z, AP_a/b/c": ("ap_p", "ap_x", "ap_y", "ap_z", "ap_a", "ap_b", "ap_c"),
    "drift dAP, dRP": ("dap_p", "dap_a", "dap_b", "dap_c", "drp_l", "drp_a", "drp_b", "drp_c"),
    "AD, RD (P2-P4)": ("ad_p", "ad_x", "ad_y", "ad_z", "ad_a", "ad_b", "ad_c", "rd_p", "rd_x", "rd_y", "rd_z",
                       "rd_a", "rd_b", "rd_c"),
    "vAP (P1, 3 directions)": ("vap_p", "vap_a", "vap_b", "vap_c"),
}


def scenarios(runs: int) -> list[tuple[str, SyntheticCell, int]]:
    return [
        ("n = 30, noise from the calibration floor", SyntheticCell(cycles=30, directions=3), runs),
        ("n = 5, noise from the calibration floor", SyntheticCell(cycles=5, directions=3), runs),
        ("n = 10, noise from 2 frames per pose", SyntheticCell(cycles=10, directions=3, frames_per_pose=2,
                                                               noise_estimator="frames"), max(runs // 2, 10)),
        ("n = 30, Student-t (5 dof) frame noise", SyntheticCell(cycles=30, directions=3, noise_tail_dof=5.0),
         max(runs // 2, 10)),
    ]


def calibration_residual_check(seeds: int = 300) -> None:
    micrometre = 1e-6
    covered, before, after = 0, [], []
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        points = np.repeat(np.arange(13), 9)
        reference = np.repeat(np.linspace(0.005, 0.065, 13), 9)
        true = rng.normal(size=13)[points] * 0.3 * micrometre + rng.normal(size=points.size) * 0.4 * micrometre
        measured = true - rng.normal(size=points.size) * 0.5 * micrometre
        f = calibration_residual_uncertainty(measured, reference, points, component="x",
                                             reference_noise=0.5 * micrometre, reference_scale=1e-6, draws=2000,
                                             seed=seed, true_residuals=true)
        covered += abs(f.value - f.true) <= f.expanded_uncertainty
        before.append(f.uncorrected_value - f.true)
        after.append(f.value - f.true)
    print(f"\n## A calibration's residual ({seeds} synthetic held-out sets)\n")
    rms_after = float(np.sqrt(np.mean(np.square(after))))
    print(f"coverage of U: {covered / seeds:.3f}; mean error before the bias step "
          f"{np.mean(before) / micrometre:+.3f} µm, after {np.mean(after) / micrometre:+.3f} µm; "
          f"RMS error after {rms_after / micrometre:.3f} µm")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=200, help="synthetic runs per scenario (default 200)")
    parser.add_argument("--draws", type=int, default=300, help="Monte Carlo draws per run (default 300)")
    parser.add_argument("--seed", type=int, default=0, help="first seed")
    parser.add_argument("--part", choices=("all", "iso", "calibration"), default="all", help="what to run")
    args = parser.parse_args(argv)
    if args.runs < 1 or args.draws < 50:
        parser.error("--runs must be ≥ 1 and --draws ≥ 50")
    if args.part != "calibration":
        iso_coverage(args)
    if args.part != "iso":
        calibration_residual_check()
    return 0


def iso_coverage(args) -> None:
    summary = []
    for title, cell, runs in scenarios(args.runs):
        started = time.perf_counter()
        cases = []
        for seed in range(args.seed, args.seed + runs):
            synthetic = synthetic_iso_run(seed, cell)
            cases.append(CoverageCase(synthetic.run, synthetic.budget, synthetic.distance_pairs,
                                      synthetic.drift_cycles))
        table = coverage_study(cases, draws=args.draws, seed=args.seed)
        elapsed = time.perf_counter() - started
        print(f"\n## {title}: {runs} runs, {args.draws} draws each ({elapsed:.0f} s)\n")
        print(table.format())
        present = {r.figure: r for r in table.rows}
        for family, names in FAMILIES.items():
            rows = [present[n] for n in names if n in present]
            if rows:
                count = sum(r.count for r in rows)
                coverage = sum(r.coverage * r.count for r in rows) / count
                low = min(r.coverage for r in rows)
                high = max(r.coverage for r in rows)
                summary.append((title, family, count, coverage, low, high))
        print("outside 93–98 %:", ", ".join(table.outside_target()) or "none")

    print("\n## Pooled per figure family (coverage of U, k = 2)\n")
    print(f"{'scenario':<42} {'figures':<26} {'n':>6} {'pooled':>7} {'min':>6} {'max':>6}")
    for title, family, count, coverage, low, high in summary:
        print(f"{title:<42} {family:<26} {count:>6} {coverage:>7.3f} {low:>6.3f} {high:>6.3f}")

    synthetic = synthetic_iso_run(args.seed, SyntheticCell(cycles=30))
    started = time.perf_counter()
    cpu = time.process_time()
    iso_uncertainty(synthetic.run, synthetic.budget, draws=1000, distance_pairs=synthetic.distance_pairs,
                    drift_cycles=synthetic.drift_cycles)
    print(f"\none full evaluation (30 cycles, 5 points, drift, P2-P4; 1000 draws + "
          f"{len(synthetic.budget.terms)} terms × 250 draws for the contributions): "
          f"{time.perf_counter() - started:.1f} s wall, {time.process_time() - cpu:.1f} s CPU")


if __name__ == "__main__":
    raise SystemExit(main())
