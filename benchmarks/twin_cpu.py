"""What the twins cost in CPU: an idle cell's processes, and the robot controller's cycle.

1. An idle simulated cell (``SimCell``, no client connected) for ``--duration`` seconds: each twin
   process's CPU as a share of one core (the suite keeps cells alive between tests, so this is paid
   for every second a cell lives).
2. The same cell with this process reading its 1 kHz interferometer feed over socketcand (the
   driver, ``drivers.interferometer``): the twin's and this process's CPU (what a run pays on both
   sides for every second the feed is connected).
3. The arm controller's cycle (the UR twin's core, in this process, no thread of its own): the CPU
   (thread time, so a loaded host inflates it little) of one 2 ms cycle at rest, while a 50 mm
   linear move runs (``time_scale`` 4: the true tool sampled on the 1 kHz truth grid, 8 samples a
   cycle) and in the ring-down after it. A cycle must cost well under its 2 ms period, or a loaded
   host makes the twin fall behind and the true tool jump.

Run: ``.venv/bin/python benchmarks/twin_cpu.py`` (prints one JSON object).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import yaml

from drivers.interferometer import create as create_interferometer
from sim_devices.cell import SimCell
from sim_devices.faults import FaultPlan
from sim_devices.ur._config import URTwinConfig
from sim_devices.ur._controller import URController
from sim_devices.ur._motion import Motion
from sim_devices.world import World, WorldConfig


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def idle_cell(duration: float) -> dict[str, float]:
    """Per twin process: percent of one core while the cell idles."""
    with SimCell(seed=1) as cell:
        pids = {name: entry["pid"] for name, entry in cell.status().items()}
        time.sleep(3.0)  # start-up done
        before = {name: _cpu_seconds(pid) for name, pid in pids.items()}
        time.sleep(duration)
        return {name: round((_cpu_seconds(pid) - before[name]) / duration * 100, 1) for name, pid in pids.items()}


def connected_feed(duration: float) -> dict[str, float]:
    """Percent of one core: the interferometer twin, and this process reading its feed."""
    with SimCell(seed=1) as cell:
        station = yaml.safe_load(cell.station_path.read_text(encoding="utf-8"))
        twin = cell.status()["interferometer"]["pid"]
        with create_interferometer(station["devices"]["interferometer"], name="interferometer"):
            time.sleep(2.0)  # connected and streaming
            twin_before, before = _cpu_seconds(twin), os.times()
            time.sleep(duration)
            twin_after, after = _cpu_seconds(twin), os.times()
    reader = (after.user + after.system) - (before.user + before.system)
    return {"twin": round((twin_after - twin_before) / duration * 100, 1),
            "driver_process": round(reader / duration * 100, 1)}


def robot_cycle() -> dict[str, float]:
    """Microseconds of CPU per controller cycle: at rest, moving, and in the ring-down after the move."""
    controller = URController(World(WorldConfig(seed=0)), URTwinConfig(time_scale=4.0), FaultPlan())
    slot = 1
    start = time.thread_time()
    for slot in range(1, 2001):
        controller.step(slot)
    rest = (time.thread_time() - start) / 2000
    target = controller.tcp_pose.copy()
    target[0, 3] += 0.05
    controller.start_motion(lambda t, q, tcp: Motion("linear", t, q, tcp, speed=0.25, accel=1.2, target_pose=target))
    moving_steps, start = 0, time.thread_time()
    while controller.run is not None and controller.run.phase == "moving":
        slot += 1
        controller.step(slot)
        moving_steps += 1
    moving = (time.thread_time() - start) / max(moving_steps, 1)
    start = time.thread_time()
    for _ in range(500):  # the ring-down: the truth is still sampled and recorded
        slot += 1
        controller.step(slot)
    ring_down = (time.thread_time() - start) / 500
    return {"rest_us": round(rest * 1e6, 1), "moving_us": round(moving * 1e6, 1),
            "ring_down_us": round(ring_down * 1e6, 1), "moving_cycles": moving_steps}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=20.0, help="seconds the idle cell is watched")
    args = parser.parse_args()
    print(json.dumps({"idle_cell_percent_of_a_core": idle_cell(args.duration),
                      "connected_feed_percent_of_a_core": connected_feed(args.duration),
                      "robot_cycle_cpu": robot_cycle()}))


if __name__ == "__main__":
    main()
