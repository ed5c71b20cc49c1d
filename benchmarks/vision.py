"""Benchmark of ``instrument.vision`` (a script, not a test): speed, precision, bias, accuracy.

Run from the repository root::

    .venv/bin/python benchmarks/vision.py            # full run (~1 min)
    .venv/bin/python benchmarks/vision.py --quick    # fewer repeats

Everything runs on one core (OMP_NUM_THREADS=1 before numpy is imported, cv2.setNumThreads(1)).
Speed is CPU time per image (time.process_time), the best and the median of 40 batches of 10 calls:
on a shared machine the best batch is the closest to the cost on an idle core; wall time is
printed too. Images come from tests/synthetic_cross.py (pixel-integrated Gaussian stripes).
"""

from __future__ import annotations

import os

os.environ["OMP_NUM_THREADS"] = "1"  # before numpy loads its BLAS

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

cv2.setNumThreads(1)
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from instrument.vision import igcf_centers, locate_cross  # noqa: E402
from tests.synthetic_cross import cramer_rao, render_cross, section_profiles  # noqa: E402

TARGETS = {
    "precision": 1.15,  # × CRB
    "bias": 0.002,  # px
    "centre": 0.01,  # px RMS
    "angle": 5.0,  # µrad RMS
    (1040, 1024): 2.0,  # ms
    (2048, 2448): 5.0,  # ms
}


def time_per_image(img, batches, per_batch, saturation=None, prior=None):
    """(best, median) CPU ms and best wall ms per call of locate_cross over ``batches`` batches."""
    locate_cross(img, saturation, prior)  # warm-up
    cpu, wall = [], []
    for _ in range(batches):
        c0, w0 = time.process_time(), time.perf_counter()
        for _ in range(per_batch):
            locate_cross(img, saturation, prior)
        cpu.append((time.process_time() - c0) / per_batch * 1e3)
        wall.append((time.perf_counter() - w0) / per_batch * 1e3)
    return min(cpu), float(np.median(cpu)), min(wall)


def section_precision(n, sigma, amplitude, noise, seed, half_window=None):
    profiles, truth = section_profiles(n, sigma=sigma, amplitude=amplitude, noise=noise, seed=seed)
    r = igcf_centers(profiles, axis=0, background=10.0, saturation=255, half_window=half_window)
    error = r.center[r.valid] - truth[r.valid]
    return float(np.std(error) / cramer_rao(sigma, amplitude, noise)), float(np.mean(error))


def saturated_bias(n, amplitude, seed):
    """Mean error over random sub-pixel phases (noisy) and the worst phase-bin mean (noise-free)."""
    profiles, truth = section_profiles(n, amplitude=amplitude, noise=2.0, seed=seed)
    r = igcf_centers(profiles, axis=0, background=10.0, saturation=255)
    error = r.center[r.valid] - truth[r.valid]
    clean, truth_c = section_profiles(2000, amplitude=amplitude, noise=0.0, seed=seed, quantize=False)
    rc = igcf_centers(clean, axis=0, background=10.0, saturation=255)
    worst_clean = float(np.max(np.abs(rc.center - truth_c)))
    return float(np.mean(error)), float(np.std(error) / np.sqrt(len(error))), worst_clean


def image_accuracy(n_images, shape, seed):
    """RMS centre (px) and angle (µrad) errors over random noisy ideal crosses."""
    rng = np.random.default_rng(seed)
    centre_err, angle_err = [], []
    for i in range(n_images):
        center = (rng.uniform(0.2, 0.8) * shape[1], rng.uniform(0.2, 0.8) * shape[0])
        angle, perpendicularity = rng.uniform(-0.55, 0.55), rng.uniform(-0.05, 0.05)
        img, truth = render_cross(shape, center, angle, perpendicularity, seed=seed + i)
        m = locate_cross(img)
        centre_err.append(np.hypot(*(m.center - truth.center)))
        angle_err.append(m.angle - truth.angle)
    return float(np.sqrt(np.mean(np.square(centre_err)))), float(np.sqrt(np.mean(np.square(angle_err))) * 1e6)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats and images")
    args = parser.parse_args(argv)
    batches, per_batch = (5, 10) if args.quick else (40, 10)
    n_sections = 5000 if args.quick else 20000
    n_images = 6 if args.quick else 20

    rows = []

    def row(what, value, target, unit, ok):
        rows.append((what, value, f"{target} {unit}", "yes" if ok else "NO"))

    twelve_bit = dict(dtype=np.uint16, saturation=4095, amplitude=3200.0, background=160.0, noise=32.0)
    for shape in [(1040, 1024), (2048, 2448)]:
        for bits, kwargs in ((8, {}), (12, twelve_bit)):
            img, _ = render_cross(shape, (0.47 * shape[1], 0.52 * shape[0]), 0.2, 0.01, seed=1, **kwargs)
            best, median, wall = time_per_image(img, batches, per_batch, kwargs.get("saturation"))
            label = f"time {shape[1]}×{shape[0]} {bits}-bit (ms/image, CPU best / median / wall best)"
            measured = f"{best:.2f} / {median:.2f} / {wall:.2f}"
            row(label, measured, f"≤ {TARGETS[shape]}", "ms", best <= TARGETS[shape])
            # tracking: the prior is the previous frame's result, the cross 6 px and 0.005 rad away
            before, _ = render_cross(shape, (0.47 * shape[1] - 4, 0.52 * shape[0] + 4.5), 0.195, 0.01, seed=2, **kwargs)
            prior = locate_cross(before, kwargs.get("saturation"))
            best, median, wall = time_per_image(img, batches, per_batch, kwargs.get("saturation"), prior)
            label = "  tracked (prior from the previous frame; CPU best / median / wall best)"
            rows.append((label, f"{best:.2f} / {median:.2f} / {wall:.2f}", "(informative)", "-"))

    for sigma, amplitude, noise in [(2.0, 200.0, 2.0), (1.5, 150.0, 3.0), (1.2, 100.0, 2.0)]:
        ratio, _ = section_precision(n_sections, sigma, amplitude, noise, seed=3)
        label = f"section precision / CRB (σ={sigma}, A={amplitude:.0f}, σn={noise})"
        row(label, f"{ratio:.3f}", f"≤ {TARGETS['precision']}", "× CRB", ratio <= TARGETS["precision"])
    # wider stripes: the 9-px window cap of method.md §2.2 covers only ±1.3σ at σ = 3
    for half_window in (None, 6):
        ratio, _ = section_precision(n_sections, 3.0, 200.0, 4.0, seed=3, half_window=half_window)
        label = f"section precision / CRB (σ=3.0, A=200, σn=4.0, window {2 * (half_window or 4) + 1} px)"
        rows.append((label, f"{ratio:.3f}", "(informative)", "-"))

    for amplitude in (400.0, 1000.0):
        bias, stderr, worst_clean = saturated_bias(n_sections, amplitude, seed=4)
        label = f"saturated bias, A={amplitude:.0f} on 255 (noisy mean ± s.e.; noise-free worst)"
        row(label, f"{bias:+.5f} ± {stderr:.5f}; {worst_clean:.1e}", f"< {TARGETS['bias']}", "px",
            abs(bias) < TARGETS["bias"])

    centre_rms, angle_rms = image_accuracy(n_images, (1040, 1024), seed=100)
    row(f"centre error, {n_images} images 1024×1040 (σ=2, A=200, σn=2, |θ|≤0.55)", f"{centre_rms:.4f}",
        f"≤ {TARGETS['centre']}", "px RMS", centre_rms <= TARGETS["centre"])
    row("angle error, same images", f"{angle_rms:.2f}", f"≤ {TARGETS['angle']}", "µrad RMS",
        angle_rms <= TARGETS["angle"])

    width = max(len(r[0]) for r in rows)
    print(f"{'figure':<{width}}  {'measured':>28}  {'target':>14}  met")
    for what, value, target, ok in rows:
        print(f"{what:<{width}}  {value:>28}  {target:>14}  {ok}")


if __name__ == "__main__":
    main()
