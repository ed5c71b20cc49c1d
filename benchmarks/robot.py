"""Robot stack figures: pose-read and short-moveL round trips through URRobot against the UR twin,
and the twin process's CPU while it streams RTDE at 500 Hz to two clients.

Run: ``OMP_NUM_THREADS=1 .venv/bin/python benchmarks/robot.py`` (prints one JSON object).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import psutil

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.robot import MotionEnvelope, URRobot, URRtdeSettings
from sim_devices import TwinProcess
from sim_devices.cell import free_loopback_host

TIME_SCALE = 10.0


def free_address() -> str:
    return free_loopback_host(first=60, last=79)


def percentiles(samples) -> dict[str, float]:
    a = np.asarray(samples) * 1e3
    return {"median_ms": round(float(np.median(a)), 3), "p95_ms": round(float(np.percentile(a, 95)), 3),
            "n": len(a)}


def main() -> None:
    host = free_address()
    twin = TwinProcess("sim_devices.ur:standalone_host", {"host": host, "time_scale": TIME_SCALE})
    twin.start()
    robot = URRobot(URRtdeSettings(host=host), name="robot", envelope=MotionEnvelope())
    try:
        robot.open()
        pid = twin._process.pid  # the child process this benchmark started
        proc = psutil.Process(pid)
        proc.cpu_percent(None)
        time.sleep(3.0)  # idle, streaming 500 Hz to the receive and the control client
        idle_cpu = proc.cpu_percent(None)

        reads = []
        for _ in range(2000):
            t0 = time.perf_counter()
            robot.tcp_pose()
            reads.append(time.perf_counter() - t0)

        start = robot.tcp_pose()
        moves = []
        for i in range(40):
            target = start + [0.0, 0.0, 0.001 * (1 if i % 2 == 0 else 0), 0.0, 0.0, 0.0]
            t0 = time.perf_counter()
            robot.move_linear(target, speed=0.25, acceleration=1.2)
            moves.append(time.perf_counter() - t0)
        move_cpu = proc.cpu_percent(None)
        # 1 mm at 0.25 m/s, 1.2 m/s² is triangular: 2·sqrt(1e-3/1.2) = 57.7 ms simulated.
        simulated = 2 * np.sqrt(1e-3 / 1.2) / TIME_SCALE
        result = {
            "command": "OMP_NUM_THREADS=1 .venv/bin/python benchmarks/robot.py",
            "time_scale": TIME_SCALE,
            "pose_read_round_trip": percentiles(reads),
            "moveL_1mm_blocking_round_trip": percentiles(moves),
            "moveL_1mm_motion_time_ms": round(simulated * 1e3, 3),
            "twin_cpu_percent_idle_streaming_500Hz_two_clients": round(idle_cpu, 1),
            "twin_cpu_percent_during_moves": round(move_cpu, 1),
            "cpus": psutil.cpu_count(),
        }
        print(json.dumps(result, indent=2))
    finally:
        robot.close()
        twin.stop()


if __name__ == "__main__":
    main()
