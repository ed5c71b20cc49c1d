"""Benchmark: error compensation on the paper-like calibration scenario (method.md §4, §6).

Run: OMP_NUM_THREADS=1 .venv/bin/python benchmarks/compensation.py [--seed N]

Prints, per component, the held-out error (k-fold over whole calibration points, and
leave-one-group-out) of CSF-PPSO-ESN next to every baseline, against the noise floor; the
error on an independent re-measurement at mid-step positions (the paper's §4.2 check: fit on
everything, then measure new points); and the fitting time per component on one core.
Targets (paper): ≤ 1.5 µm and ≤ 2″ after compensation; aim: the noise floor.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

from instrument.compensation import (
    COMPONENTS,
    CsfPpsoEsnCompensator,
    SmoothingSplineCompensator,
    default_compensators,
    display_unit,
    evaluate,
    paper_like_scenario,
)


def independent_check(scenario, compensators, seed):
    """Fit on all calibration data; score on fresh points half-way between calibration points,
    measured from group 0's start pose (no offset), 3 repeats each, noise as in the calibration."""
    rng = np.random.default_rng(seed + 1000)
    rows = []
    for component in COMPONENTS:
        data = scenario.data[component]
        lo, hi = data.measured.min(), data.measured.max()
        true_value = np.linspace(lo, hi, 29)[1:-1:2]  # 14 mid-step positions
        true_value = np.repeat(true_value, 3)
        sigma = scenario.noise_sigma[component]
        error = scenario.true_error[component](true_value) + rng.normal(0.0, sigma, true_value.size)
        measured = true_value + error
        for name, comp in compensators.items():
            model = comp.fit(data.measured, data.error, data.group, data.point)
            residual = error - model.predict(measured)
            rows.append((component, name, float(np.sqrt(np.mean(residual**2))), float(np.abs(residual).max()), sigma))
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    scenario = paper_like_scenario(seed=args.seed)
    compensators = default_compensators(seed=args.seed)
    compensators["csf-ppso-esn(min-heldout)"] = CsfPpsoEsnCompensator(seed=args.seed, selection="min_heldout",
                                                                      name="csf-ppso-esn(min-heldout)")
    compensators["csf+poly2"] = SmoothingSplineCompensator(trend_degree=2)

    print(f"paper-like scenario, seed {args.seed}: 15 points x 3 repeats x 3 groups per component\n")
    print("fitting time per component on all 135 observations (one core):")
    for name, comp in compensators.items():
        times = []
        for component in COMPONENTS:
            d = scenario.data[component]
            t0 = time.perf_counter()
            comp.fit(d.measured, d.error, d.group, d.point)
            times.append(time.perf_counter() - t0)
        print(f"  {name:28s} mean {np.mean(times):7.3f} s   max {np.max(times):7.3f} s")

    t0 = time.perf_counter()
    table = evaluate(compensators, scenario.data)
    print(f"\nheld-out evaluation ({time.perf_counter() - t0:.0f} s):")
    print(table.format())
    print("\nwinner per component (k-fold held-out RMS):")
    for component in COMPONENTS:
        best = table.row(component, table.best(component))
        esn = table.row(component, "csf-ppso-esn")
        unit, f = display_unit(component)
        print(f"  {component}: {best.method:28s} {best.rms * f:6.3f} {unit} RMS ({best.ratio_to_floor:.2f} x floor); "
              f"csf-ppso-esn {esn.rms * f:6.3f} ({esn.ratio_to_floor:.2f} x)")

    print("\nindependent re-measurement at mid-step positions (fit on all data; RMS / max; floor):")
    for component, name, rms, worst, sigma in independent_check(scenario, compensators, args.seed):
        unit, f = display_unit(component)
        print(f"  {component} {name:28s} {rms * f:7.3f} / {worst * f:7.3f} {unit}   floor {sigma * f:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
