"""Pose solver benchmark: time per solve, and how far the paper's closed form departs from it.

Run: OMP_NUM_THREADS=1 .venv/bin/python benchmarks/pose.py
(the Makefile's ``make bench`` sets OMP_NUM_THREADS=1 for every benchmark).

Station: screens at 0.25 m, cameras imaging ~160 mm onto 1024 × 1040 px (0.156 mm/px), mirrored
and turned by odd angles, with a little perspective. Crosses come from the exact forward model
(``predict_measurements``), so the exact solver's own error is ~1e-15 and every departure shown
is the closed form's.
"""

from __future__ import annotations

import os
import time

import numpy as np

from instrument.iso9283 import pose_repeatability
from instrument.pose import (
    Geometry,
    Pose,
    make_homography,
    observe_crosses,
    predict_measurements,
    small_motion_pose,
    solve_pose,
)

METRES_PER_PIXEL = 0.160 / 1024
CAMERAS = {
    "x": (np.radians(37.0), True, (3e-5, -2e-5)),
    "y": (np.radians(-128.0), False, (-1e-5, 2e-5)),
    "z": (np.radians(90.0), True, (0.0, 1e-5)),
}
AXES = {
    "x": ([0.25, 0, 0], [0, 1, 0], [0, 0, 1]),
    "y": ([0, 0.25, 0], [0, 0, 1], [1, 0, 0]),
    "z": ([0, 0, 0.25], [1, 0, 0], [0, 1, 0]),
}


def station() -> Geometry:
    screens = {}
    for name, (origin, u, v) in AXES.items():
        rotation, mirrored, perspective = CAMERAS[name]
        homography = make_homography(METRES_PER_PIXEL, rotation=rotation, mirrored=mirrored, perspective=perspective)
        screens[name] = {
            "origin": origin,
            "u": u,
            "v": v,
            "pixel_to_screen": homography.tolist(),
            "size_px": [1024, 1040],
        }
    return Geometry.from_dict({"screens": screens})


def random_direction(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def time_solver(geometry: Geometry, repeats: int = 2000) -> dict[str, tuple[float, float]]:
    rng = np.random.default_rng(1)
    cases = []
    for _ in range(20):
        pose = Pose.from_euler(rng.uniform(-0.05, 0.05, 3), np.radians(rng.uniform(-2, 2, 3)))
        cases.append(predict_measurements(pose, geometry, noise_px=0.02, rng=rng))
    timings = {}
    # a stream's warm start: the previous frame's pose, 0.1 mm and 0.0006° away
    solved = {id(m): solve_pose(m, geometry).pose for m in cases}
    previous = {key: Pose.from_euler(p.translation + 1e-4, p.euler + 1e-5) for key, p in solved.items()}
    for label, prepare in (
        ("solve_pose(CrossMeasurement)", lambda m: m),
        ("solve_pose(CrossMeasurement), warm start", "warm"),
        ("solve_pose(ScreenCross)", lambda m: observe_crosses(m, geometry)),
        ("small_motion_pose", None),
    ):
        inputs = [prepare(m) if callable(prepare) else m for m in cases]
        if prepare == "warm":
            function = lambda m: solve_pose(m, geometry, initial=previous[id(m)])
        elif prepare is None:
            function = lambda m: small_motion_pose(m, geometry)
        else:
            function = lambda m: solve_pose(m, geometry)
        for m in inputs:  # warm up
            function(m)
        # CPU time of this process (what one core spends, whatever else runs on the machine) and
        # the best wall-clock time of 20 short batches (the least disturbed by other processes).
        batch = max(repeats // 20, 1)
        best_wall, cpu_total = np.inf, 0.0
        for _ in range(20):
            wall, cpu = time.perf_counter(), time.process_time()
            for i in range(batch):
                function(inputs[i % len(inputs)])
            cpu_total += time.process_time() - cpu
            best_wall = min(best_wall, (time.perf_counter() - wall) / batch)
        timings[label] = (cpu_total / (20 * batch) * 1e3, best_wall * 1e3)
    return timings


def departure_table(geometry: Geometry, trials: int = 40):
    """Worst closed-form error over random directions, per (|t|, rotation angle)."""
    rng = np.random.default_rng(7)
    rows = []
    for translation_mm in (0.0, 1.0, 10.0, 50.0):
        for rotation_deg in (0.0, 0.1, 0.5, 2.0, 5.0):
            worst = {"paper": [0.0, 0.0], "exact": [0.0, 0.0]}
            for _ in range(trials):
                t = translation_mm * 1e-3 * random_direction(rng)
                rotvec = np.radians(rotation_deg) * random_direction(rng)
                truth = Pose.from_rotvec_pose(np.r_[t, rotvec])
                crosses = observe_crosses(predict_measurements(truth, geometry), geometry)
                exact = solve_pose(crosses, geometry)
                assert np.abs(exact.translation - truth.translation).max() < 1e-9
                for lever in worst:
                    estimate = small_motion_pose(crosses, geometry, lever=lever)
                    worst[lever][0] = max(
                        worst[lever][0], float(np.abs(estimate.translation - truth.translation).max())
                    )
                    worst[lever][1] = max(worst[lever][1], float(np.abs(estimate.euler - truth.euler).max()))
            rows.append((translation_mm, rotation_deg, worst))
    return rows


def rp_l_interval_coverage(trials: int = 400, n: int = 30) -> dict[str, float]:
    """Coverage of the population RP_l (μ_l + 3σ_l) by 95 % intervals, Gaussian scatter, n poses."""
    rng = np.random.default_rng(11)
    cases = {"isotropic": np.ones(3), "anisotropic 1:0.5:2": np.array([1.0, 0.5, 2.0])}
    out = {}
    for label, scale in cases.items():
        big = np.linalg.norm(rng.normal(size=(2_000_000, 3)) * scale, axis=1)
        population = big.mean() + 3.0 * big.std()
        hits_t = hits_percentile = 0
        for trial in range(trials):
            positions = rng.normal(size=(n, 3)) * scale
            poses = np.column_stack([positions, np.zeros((n, 3))])
            low, high = pose_repeatability(poses, confidence=0.95, seed=trial).rp_l_ci
            hits_t += low <= population <= high
            # the plain percentile bootstrap, for comparison
            resampled = positions[np.random.default_rng(trial).integers(0, n, (2000, n))]
            distances = np.linalg.norm(resampled - resampled.mean(axis=1, keepdims=True), axis=2)
            boot = distances.mean(axis=1) + 3.0 * distances.std(axis=1, ddof=1)
            p_low, p_high = np.quantile(boot, [0.025, 0.975])
            hits_percentile += p_low <= population <= p_high
        out[label] = (hits_t / trials, hits_percentile / trials)
    return out


def main() -> None:
    geometry = station()
    print(f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}")
    print("time per call, ms: mean CPU time | best wall-clock batch")
    for label, (cpu_ms, wall_ms) in time_solver(geometry).items():
        print(f"  {label:32s} {cpu_ms:7.3f} | {wall_ms:7.3f}")
    print()
    print("closed form vs exact solver: worst |error| over 40 random directions per row")
    print(
        "| |t| (mm) | rotation (°) | paper lever: position (µm) | angle (″) | exact lever: position (µm) | angle (″) |"
    )
    print("| ---: | ---: | ---: | ---: | ---: | ---: |")
    for translation_mm, rotation_deg, worst in departure_table(geometry):
        paper, exact = worst["paper"], worst["exact"]
        print(
            f"| {translation_mm:g} | {rotation_deg:g} | {paper[0] * 1e6:.3g} | {np.degrees(paper[1]) * 3600:.3g} "
            f"| {exact[0] * 1e6:.3g} | {np.degrees(exact[1]) * 3600:.3g} |"
        )
    print()
    print("ISO 9283 RP_l 95 % interval coverage, n = 30, 400 trials (bootstrap-t as shipped | plain percentile):")
    for label, (student, percentile) in rp_l_interval_coverage().items():
        print(f"  {label:22s} {student:.3f} | {percentile:.3f}")


if __name__ == "__main__":
    main()
