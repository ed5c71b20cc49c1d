"""Camera benchmark: render time per frame (1 MP and 5 MP) and triplets/s through the pylon emulator.

Run: ``OMP_NUM_THREADS=1 .venv/bin/python benchmarks/cameras.py`` (prints one JSON object).
Targets: ≥ 30 triplets/s through the emulator; 3 frames of 5 MP rendered well under 1 s.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.camera import create_triplet
from sim_devices._transforms import euler_to_matrix, make_transform
from sim_devices.camera import CameraFileTwin, OpticalBench, Renderer
from sim_devices.world import World, WorldConfig

POSE = make_transform(euler_to_matrix(*np.radians([0.5, -0.3, 0.8])), [0.035, 0.020, 0.050])


def render_time(bench: OpticalBench, repeats: int = 10) -> float:
    """Median seconds per frame (noise, speckle, quantisation included)."""
    renderer = Renderer(bench, seed=1)
    renderer.render_all(POSE, seq=0)  # warm caches (background images)
    times = []
    for seq in range(1, repeats + 1):
        for name in "xyz":
            start = time.perf_counter()
            renderer.render(name, POSE, seq=seq)
            times.append(time.perf_counter() - start)
    return float(np.median(times))


def emulator_rates(seconds: float = 3.0) -> dict[str, float]:
    world = World(WorldConfig(seed=1))
    bench = OpticalBench(world)
    with tempfile.TemporaryDirectory() as directory:
        twin = CameraFileTwin(world, bench, directory)
        twin.start()
        serials = {"x": "0815-0000", "y": "0815-0001", "z": "0815-0002"}
        triplet = create_triplet({k: {"adapter": "pylon", "serial": s, "emulator_image": str(twin.paths[k])}
                                  for k, s in serials.items()})
        with triplet:
            triplet.grab()
            count, start = 0, time.perf_counter()
            while time.perf_counter() - start < seconds:
                triplet.grab()
                count += 1
            static = count / (time.perf_counter() - start)
            # Move → settle (render + write 3 BMPs) → grab (emulator reloads the files), as a run does.
            count, start = 0, time.perf_counter()
            flange = world.flange_pose()
            while time.perf_counter() - start < seconds:
                flange[:3, 3] += [1e-4, 0.0, 0.0]
                world.set_flange_pose(flange)
                triplet.grab()
                count += 1
            moving = count / (time.perf_counter() - start)
        twin.stop()
    return {"triplets_per_s_static_pose": static, "move_render_grab_cycles_per_s": moving}


def main() -> None:
    world = World(WorldConfig(seed=1))
    one_mp = OpticalBench(world)
    five_mp = OpticalBench(world, {"size_px": [2448, 2048], "metres_per_px": 0.156e-3 * 1024 / 2448})
    result = {
        "render_s_per_frame_1024x1040": render_time(one_mp),
        "render_s_per_frame_2448x2048": render_time(five_mp, repeats=4),
        **emulator_rates(),
    }
    print(json.dumps({k: round(v, 4) for k, v in result.items()}, indent=1))
    if result["triplets_per_s_static_pose"] < 30:
        print("below target: 30 triplets/s", file=sys.stderr)


if __name__ == "__main__":
    main()
