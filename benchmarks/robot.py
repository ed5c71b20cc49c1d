"""Robot stack figures: pose-read, state-read and short-moveL round trips through URRobot against the
UR twin, the cost of opening (worker process start, probe and ur_rtde handshakes), and the twin
process's CPU while it streams RTDE at 500 Hz to two clients.

Since the ur_rtde clients live in a worker process, every call is one pipe round trip to it.

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


def timed(call, repeats: int) -> list[float]:
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        call()
        samples.append(time.perf_counter() - t0)
    return samples


def main() -> None:
    host = free_address()
    twin = TwinProcess("sim_devices.ur:standalone_host", {"host": host, "time_scale": TIME_SCALE})
    twin.start()
    robot = URRobot(URRtdeSettings(host=host), name="robot", envelope=MotionEnvelope())
    try:
        opens = []
        for _ in range(3):
            t0 = time.perf_counter()
            robot.open()
            opens.append(time.perf_counter() - t0)
            robot.close()
        robot.open()
        pid = twin._process.pid  # the child process this benchmark started
        proc = psutil.Process(pid)
        proc.cpu_percent(None)
        time.sleep(3.0)  # idle, streaming 500 Hz to the receive and the control client
        idle_cpu = proc.cpu_percent(None)

        reads = timed(robot.tcp_pose, 2000)
        states = timed(robot.state, 500)
        identities = timed(robot.identity, 20)

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
            "open_worker_start_probe_and_handshakes": percentiles(opens),
            "pose_read_round_trip": percentiles(reads),
            "state_read_round_trip": percentiles(states),
            "identity_read_round_trip": percentiles(identities),
            "moveL_1mm_blocking_round_trip": percentiles(moves),
            "moveL_1mm_motion_time_ms": round(simulated * 1e3, 3),
            "twin_cpu_percent_idle_streaming_500Hz_two_clients": round(idle_cpu, 1),
            "twin_cpu_percent_during_moves": round(move_cpu, 1),
            "cpus": psutil.cpu_count(),
            "load_average_1min": round(psutil.getloadavg()[0], 2),
        }
        print(json.dumps(result, indent=2))
    finally:
        robot.close()
        twin.stop()


if __name__ == "__main__":
    main()
