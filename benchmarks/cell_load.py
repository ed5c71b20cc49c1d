"""The whole simulated cell under load: the RTDE stream, the CAN feed and moveL latency.

Starts ``--burners`` CPU burners (busy loops, one process and session each, as if started from
other shells; two saturate this 2-core VM), then

1. a UR twin alone (its own process): ``--moves`` blocking 10 mm moveL through ur_rtde;
2. the whole cell (``SimCell``: one process per twin) for ``--duration`` seconds while a ur_rtde
   control client moves the arm back and forth by 10 mm without pause (so the world publishes a
   settled pose, the camera twin renders three frames and the interferometer sees it, every move),
   and measures

   Each measuring client runs in a process of its own, as a lab host would run its drivers (one
   Python process reading two 1 kHz feeds and a 500 Hz stream would measure its own GIL):

   - RTDE: every data package of one connection (``tests/rtde_probe.py``): packages per wall
     second, missing 2 ms slots, and packages not from one controller state (actual/target TCP pose
     not the forward kinematics of that package's actual/target joints; 'done' with a pose that is
     not a move's end pose);
   - CAN: python-can through the interferometer adapter on socketcand and slcan at once: rate,
     counter gaps (lost samples) and the p99 of |interval − 1 ms| on the frames' timestamps
     (socketcand's own, slcan's host receive stamps);
   - moveL latency in the cell, against the standalone figure of step 1.

    .venv/bin/python benchmarks/cell_load.py                         # 60 s, two burners
    .venv/bin/python benchmarks/cell_load.py --duration 20 --burners 0

Targets (issue 15): RTDE ≥ 475 packages/s, every package consistent; CAN 1 kHz with no counter
gaps and timestamp jitter p99 ≤ 2 ms on both transports. Timing is measured here, never in tests.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers import DeviceError
from drivers.interferometer import create as create_interferometer
from sim_devices import TwinProcess
from sim_devices._transforms import pose6_to_matrix
from sim_devices.cell import SimCell, free_loopback_host
from sim_devices.ur import _kinematics as kin
from tests.rtde_probe import RTDEProbe

PROBE_FIELDS = ["timestamp", "actual_q", "target_q", "actual_TCP_pose", "target_TCP_pose", "output_int_register_0"]
MOVE = 0.010  # m, along base x, back and forth
SPEED, ACCELERATION = 0.25, 1.2


def _burn(stop) -> None:
    os.setsid()  # as if started from another shell: a session (and scheduling group) of its own
    while not stop.is_set():
        for _ in range(100_000):
            pass


class Burners:
    """``count`` busy-loop processes, started and stopped by this benchmark only."""

    def __init__(self, count: int) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._stop = ctx.Event()
        self._processes = [ctx.Process(target=_burn, args=(self._stop,), daemon=True) for _ in range(count)]

    def __enter__(self) -> Burners:
        for process in self._processes:
            process.start()
        time.sleep(0.5 if self._processes else 0.0)
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        for process in self._processes:
            process.join(5.0)
            if process.is_alive():
                process.terminate()
                process.join(5.0)


def move_latencies(control, moves: int, stop: threading.Event | None = None) -> list[float]:
    start = control.getForwardKinematics()
    latencies = []
    for i in range(moves):
        if stop is not None and stop.is_set():
            break
        target = [start[0] + MOVE * (i % 2 == 0), *start[1:]]
        t0 = time.perf_counter()
        if not control.moveL(target, SPEED, ACCELERATION):
            raise RuntimeError("moveL failed")
        latencies.append(time.perf_counter() - t0)
    return latencies


def standalone_latency(moves: int) -> list[float]:
    import rtde_control

    host = free_loopback_host(first=200, last=220)
    with TwinProcess("sim_devices.ur:standalone_host", {"host": host, "time_scale": 1.0}) as twin:
        control = rtde_control.RTDEControlInterface(twin.endpoints["host"])
        try:
            return move_latencies(control, moves)
        finally:
            control.disconnect()


def client_process(realtime: bool) -> None:
    """A measuring client's process: a session of its own, and SCHED_RR if asked (and allowed)."""
    os.setsid()
    if realtime:
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(10))


def normal_priority() -> None:
    if os.sched_getscheduler(0) != os.SCHED_OTHER:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def collect_feed(config: dict, duration: float, results, realtime: bool) -> None:
    """In its own process and session (a lab host's driver process): every sample of one transport."""
    client_process(realtime)
    name = config["adapter"]
    stamps: list[float] = []
    error = None
    device = create_interferometer(config, name=name)
    try:
        device.open()
        time.sleep(0.5)
        before = device.stats()
        end = time.monotonic() + duration
        for sample in device.samples(timeout=2.0):
            stamps.append(sample.timestamp)
            if time.monotonic() >= end:
                break
        after = device.stats()
    except DeviceError as exc:
        error, after, before = str(exc), {"lost_samples": 0, "gaps": 0}, {"lost_samples": 0, "gaps": 0}
    finally:
        device.close()
    normal_priority()
    a = np.array(stamps)
    jitter = np.abs(np.diff(a) - 1e-3) * 1e3 if len(a) > 1 else np.array([np.nan])
    results.put({"name": name, "samples": len(a), "rate": (len(a) - 1) / (a[-1] - a[0]) if len(a) > 1 else 0.0,
                 "lost": after["lost_samples"] - before["lost_samples"], "gaps": after["gaps"] - before["gaps"],
                 "jitter_p99": float(np.percentile(jitter, 99)), "jitter_max": float(np.max(jitter)),
                 "error": error})


def collect_rtde(host: str, duration: float, ends: list[list[float]], results, realtime: bool) -> None:
    """In its own process and session: every RTDE package of one connection for ``duration`` s, checked."""
    client_process(realtime)
    with RTDEProbe(host, PROBE_FIELDS) as probe:
        time.sleep(duration)
        packages = probe.take()
    normal_priority()  # seconds of forward kinematics follow: not at real-time priority
    results.put({"name": "rtde", **check_packages(packages, ends)})


def check_packages(packages, ends: list[list[float]]) -> dict[str, float]:
    stamps = np.array([p.values["timestamp"] for p in packages])
    arrivals = np.array([p.arrived for p in packages])
    slots = np.round(stamps / 0.002).astype(int)
    inconsistent = done_not_final = 0
    end_poses = [pose6_to_matrix(e) for e in ends]
    for p in packages:
        v = p.values
        if not (np.allclose(kin.forward(v["actual_q"]), pose6_to_matrix(v["actual_TCP_pose"]), atol=1e-9)
                and np.allclose(kin.forward(v["target_q"]), pose6_to_matrix(v["target_TCP_pose"]), atol=1e-9)):
            inconsistent += 1
        if v["output_int_register_0"] == 2:
            pose = pose6_to_matrix(v["actual_TCP_pose"])
            done_not_final += not any(np.allclose(pose, end, atol=1e-9) for end in end_poses)
    return {"packages": len(packages), "rate": (len(packages) - 1) / (arrivals[-1] - arrivals[0]),
            "missing_slots": int(np.sum(np.diff(slots) - 1)), "inconsistent": inconsistent,
            "done_not_final": done_not_final}


def percentiles(values, scale: float = 1e3) -> str:
    a = np.asarray(values) * scale
    return f"median {np.median(a):.1f} ms, p95 {np.percentile(a, 95):.1f} ms, max {np.max(a):.1f} ms, n {len(a)}"


def run(duration: float, burners: int, moves: int, seed: int, realtime_clients: bool) -> int:
    import rtde_control

    ctx = multiprocessing.get_context("spawn")
    with Burners(burners):
        alone = standalone_latency(moves)
        with SimCell(seed=seed, time_scale=1.0) as cell:
            host = cell.endpoints["robot"]["host"]
            ifm = cell.endpoints["interferometer"]
            control = rtde_control.RTDEControlInterface(host)
            try:
                start = control.getForwardKinematics()
                ends = [start, [start[0] + MOVE, *start[1:]]]
                results = ctx.Queue()
                clients = [ctx.Process(target=collect_rtde, args=(host, duration, ends, results, realtime_clients),
                                       daemon=True)]
                for config in ({"adapter": "socketcand", **ifm["socketcand"]},
                               {"adapter": "slcan", "port": ifm["slcan"]["port"]}):
                    clients.append(ctx.Process(target=collect_feed, args=(config, duration, results, realtime_clients),
                                               daemon=True))
                realtime_twins = [name for name, entry in cell.status().items() if entry["realtime"]]
                robot_before = cell.forward("robot", "state")
                visits_before = len(cell.forward("robot", "visits"))
                cameras_before = cell.forward("cameras", "stats")
                feed_before = cell.forward("interferometer", "stats")
                for client in clients:
                    client.start()
                time.sleep(1.0)  # the clients connect and settle
                stop = threading.Event()
                in_cell: list[float] = []
                mover = threading.Thread(target=lambda: in_cell.extend(move_latencies(control, 10**9, stop)),
                                         daemon=True)
                mover.start()
                measured = {}
                for _ in clients:
                    result = results.get(timeout=duration + 60.0)
                    measured[result["name"]] = result
                stop.set()
                mover.join(30.0)
                for client in clients:
                    client.join(10.0)
                robot_after = cell.forward("robot", "state")
                visits = cell.forward("robot", "visits", since=visits_before)
                cameras_after = cell.forward("cameras", "stats")
                feed_after = cell.forward("interferometer", "stats")
            finally:
                control.disconnect()

    rtde = measured["rtde"]
    print(f"simulated cell under load: {burners} CPU burner(s), {duration:.0f} s, seed {seed}, time scale 1; "
          f"twins under SCHED_RR: {', '.join(realtime_twins) or 'none'}; each measuring client in a process "
          f"(and session) of its own, {'SCHED_RR' if realtime_clients else 'normal priority'}")
    print(f"RTDE (one connection, every package): {rtde['rate']:.1f} packages/s, {rtde['packages']} packages, "
          f"{rtde['missing_slots']} missing slots, {rtde['inconsistent']} not from one state, "
          f"{rtde['done_not_final']} 'done' with a pose that is no move's end")
    skipped = robot_after["skipped_cycles"] - robot_before["skipped_cycles"]
    late = robot_after["late_cycles"] - robot_before["late_cycles"]
    print(f"  controller: {late} late cycles caught up, {skipped} cycles skipped by a resync")
    failed = rtde["rate"] < 475 or rtde["inconsistent"] > 0 or rtde["done_not_final"] > 0
    header = f"{'CAN':<11} {'samples':>8} {'rate Hz':>8} {'lost':>5} {'gaps':>5} {'|Δt−1ms| p99 ms':>16} {'max ms':>8}"
    print(header)
    for name in ("socketcand", "slcan"):
        r = measured[name]
        print(f"{name:<11} {r['samples']:>8} {r['rate']:>8.1f} {r['lost']:>5} {r['gaps']:>5} {r['jitter_p99']:>16.3f} "
              f"{r['jitter_max']:>8.3f}")
        if r["error"]:
            print(f"  {name}: feed error: {r['error']}")
        failed |= bool(r["error"]) or r["lost"] > 0 or r["gaps"] > 0 or r["rate"] < 990 or r["jitter_p99"] > 2.0
    twin = {key: feed_after[key] - feed_before[key] for key in feed_after
            if isinstance(feed_after[key], int) and isinstance(feed_before.get(key), int)}
    print("  interferometer twin: " + ", ".join(f"{k} {v}" for k, v in sorted(twin.items())))
    written = cameras_after["frames_written"] - cameras_before["frames_written"]
    ahead = cameras_after["rendered_ahead"] - cameras_before["rendered_ahead"]
    print(f"cameras: {written} frame sets rendered, {ahead} of them started before their pose settled")
    label = f"moveL 10 mm ({SPEED} m/s, {ACCELERATION} m/s², ur_rtde, blocking)"
    print(f"{label} standalone: {percentiles(alone)}")
    print(f"{label} in the cell: {percentiles(in_cell)}")
    waits = [v["publish_wait"] for v in visits]
    print(f"  of which waiting for every twin to see the settled pose: {percentiles(waits)}")
    print("targets (RTDE ≥ 475/s and consistent; CAN 1 kHz, no gaps, jitter p99 ≤ 2 ms):",
          "NOT MET" if failed else "met")
    return 1 if failed else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of the loaded cell (default 60)")
    parser.add_argument("--burners", type=int, default=2, help="CPU burner processes (default 2)")
    parser.add_argument("--moves", type=int, default=30, help="moves of the standalone twin (default 30)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--realtime-clients", action="store_true",
                        help="run the measuring clients under SCHED_RR, as a data-acquisition host's readers would "
                             "(slcan's timestamps are the client's receive times)")
    args = parser.parse_args(argv)
    if not args.duration > 0 or args.burners < 0 or args.moves < 2:
        parser.error("--duration must be > 0, --burners ≥ 0, --moves ≥ 2")
    return run(args.duration, args.burners, args.moves, args.seed, args.realtime_clients)


if __name__ == "__main__":
    sys.exit(main())
