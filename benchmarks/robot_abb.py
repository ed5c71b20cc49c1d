"""ABB stack figures against the IRC5 twin in its own process: the RWS round trip of the real client,
the overhead of a blocking moveL through ABBRobot (a motion program per move: upload, start,
watch, event log, joint log), and the EGM stream's rate and jitter as the real EGM client sees it.

Run: ``OMP_NUM_THREADS=1 .venv/bin/python benchmarks/robot_abb.py`` (prints one JSON object); set
``SIM_LOOPBACK_BLOCK`` to keep clear of other twins on this machine.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from abb_robot_client.egm import EGM
from abb_robot_client.rws import RWS

from drivers.robot import ABBRobot, ABBRwsSettings, MotionEnvelope
from sim_devices import TwinProcess
from sim_devices.cell import free_loopback_host

TIME_SCALE = 10.0
MOVE = 0.001  # m: the moveL of the overhead figure
EGM_SECONDS = 10.0


def percentiles(samples) -> dict[str, float]:
    a = np.asarray(samples) * 1e3
    return {"median_ms": round(float(np.median(a)), 3), "p95_ms": round(float(np.percentile(a, 95)), 3),
            "p99_ms": round(float(np.percentile(a, 99)), 3), "n": len(a)}


def egm_figures(host: str) -> dict[str, float]:
    client = EGM.__new__(EGM)  # the client's receive code on a loopback socket (it binds '' itself)
    client.socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client.socket.bind((host, 6510))
    client.send_sequence_number, client.egm_addr, client.count = 0, None, 0
    try:
        arrivals, seqnos = [], []
        end = time.monotonic() + EGM_SECONDS
        while time.monotonic() < end:
            ok, state = client.receive_from_robot(0.5)
            if ok:
                arrivals.append(time.perf_counter())
                seqnos.append(state.robot_message.header.seqno)
        gaps = np.diff(arrivals)
        return {"packets": len(seqnos), "rate_hz": round(len(seqnos) / (arrivals[-1] - arrivals[0]), 2),
                "missing_seqnos": int(np.sum(np.diff(seqnos) - 1)),
                "interval": percentiles(gaps), "interval_max_ms": round(float(gaps.max()) * 1e3, 3)}
    finally:
        client.close()


def main() -> None:
    host = free_loopback_host(first=210, last=229, tcp_ports=(80,), udp_ports=(6510,))
    twin = TwinProcess("sim_devices.abb:standalone_host", {"host": host, "time_scale": TIME_SCALE})
    twin.start()
    figures: dict[str, object] = {"time_scale": TIME_SCALE, "load_average": os.getloadavg()}
    try:
        figures["egm"] = egm_figures(host)  # before any other client: the stream alone
        rws = RWS(twin.endpoints["base_url"])
        rws.get_execution_state()  # the Digest challenge and the session, once
        samples = []
        for _ in range(300):
            t0 = time.perf_counter()
            rws.get_execution_state()
            samples.append(time.perf_counter() - t0)
        figures["rws_get_execution_state"] = percentiles(samples)
        rws.close()
        envelope = MotionEnvelope.from_dict({"box_min": [0.5, -0.5, 0.4], "box_max": [1.4, 0.5, 1.4],
                                             "max_tilt": 0.6, "max_speed": 1.0, "max_acceleration": 3.0})
        robot = ABBRobot(ABBRwsSettings(base_url=twin.endpoints["base_url"]), name="robot", envelope=envelope)
        t0 = time.perf_counter()
        robot.open()
        figures["open_s"] = round(time.perf_counter() - t0, 3)
        try:
            start = robot.tcp_pose()
            moves = []
            for i in range(40):
                target = start + [0.0, 0.0, MOVE * (i % 2 == 0), 0.0, 0.0, 0.0]
                t0 = time.perf_counter()
                robot.move_linear(target, speed=0.25)
                moves.append(time.perf_counter() - t0)
            reads = []
            for _ in range(100):
                t0 = time.perf_counter()
                robot.tcp_pose()
                reads.append(time.perf_counter() - t0)
            visits = twin.call("visits")[-40:]
            motion = [v["settling_time"] for v in visits]  # simulated s of servo settling after the profile
            figures["move_linear_1mm"] = percentiles(moves)
            figures["move_linear_servo_settling_sim_s"] = round(float(np.median(motion)), 4)
            figures["tcp_pose"] = percentiles(reads)
        finally:
            robot.close()
    finally:
        twin.stop()
    print(json.dumps(figures, indent=1))


if __name__ == "__main__":
    main()
