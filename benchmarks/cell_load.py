"""The whole simulated cell under load: the RTDE stream, the CAN feed and moveL latency.

Starts ``--burners`` CPU burners (busy loops, one process each; two saturate this 2-core VM), then

1. a UR twin alone (its own process): ``--moves`` blocking 10 mm moveL through ur_rtde;
2. the whole cell (``SimCell``: one process per twin) for ``--duration`` seconds while a ur_rtde
   control client moves the arm back and forth by 10 mm without pause (so the world publishes a
   settled pose, the camera twin renders three frames and the interferometer sees it, every move),
   and measures

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


class FeedCollector(threading.Thread):
    def __init__(self, device, duration: float) -> None:
        super().__init__(name=f"collect {device.name}", daemon=True)
        self.device, self.duration = device, duration
        self.stamps: list[float] = []
        self.error: str | None = None

    def run(self) -> None:
        end = time.monotonic() + self.duration
        try:
            for sample in self.device.samples(timeout=2.0):
                self.stamps.append(sample.timestamp)
                if time.monotonic() >= end:
                    break
        except DeviceError as exc:
            self.error = str(exc)


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


def run(duration: float, burners: int, moves: int, seed: int) -> int:
    import rtde_control

    with Burners(burners):
        alone = standalone_latency(moves)
        with SimCell(seed=seed, time_scale=1.0) as cell:
            host = cell.endpoints["robot"]["host"]
            ifm = cell.endpoints["interferometer"]
            feeds = {"socketcand": create_interferometer({"adapter": "socketcand", **ifm["socketcand"]},
                                                         name="socketcand"),
                     "slcan": create_interferometer({"adapter": "slcan", "port": ifm["slcan"]["port"]}, name="slcan")}
            control = rtde_control.RTDEControlInterface(host)
            start = control.getForwardKinematics()
            ends = [start, [start[0] + MOVE, *start[1:]]]
            for feed in feeds.values():
                feed.open()
            robot_before = cell.forward("robot", "state")
            cameras_before = cell.forward("cameras", "stats")
            try:
                time.sleep(0.5)
                before = {name: feed.stats() for name, feed in feeds.items()}
                collectors = {name: FeedCollector(feed, duration) for name, feed in feeds.items()}
                stop = threading.Event()
                in_cell: list[float] = []
                mover = threading.Thread(target=lambda: in_cell.extend(move_latencies(control, 10**9, stop)),
                                         daemon=True)
                with RTDEProbe(host, PROBE_FIELDS) as probe:
                    for collector in collectors.values():
                        collector.start()
                    mover.start()
                    time.sleep(duration)
                    stop.set()
                    mover.join(30.0)
                    packages = probe.take()
                for collector in collectors.values():
                    collector.join(duration + 10.0)
                after = {name: feed.stats() for name, feed in feeds.items()}
                robot_after = cell.forward("robot", "state")
                cameras_after = cell.forward("cameras", "stats")
            finally:
                for feed in feeds.values():
                    feed.close()
                control.disconnect()

    rtde = check_packages(packages, ends)
    print(f"simulated cell under load: {burners} CPU burner(s), {duration:.0f} s, seed {seed}, time scale 1")
    print(f"RTDE (one connection, every package): {rtde['rate']:.1f} packages/s, {rtde['packages']} packages, "
          f"{rtde['missing_slots']} missing slots, {rtde['inconsistent']} not from one state, "
          f"{rtde['done_not_final']} 'done' with a pose that is no move's end")
    skipped = robot_after["skipped_cycles"] - robot_before["skipped_cycles"]
    late = robot_after["late_cycles"] - robot_before["late_cycles"]
    print(f"  controller: {late} late cycles caught up, {skipped} cycles skipped by a resync")
    failed = rtde["rate"] < 475 or rtde["inconsistent"] or rtde["done_not_final"]
    header = f"{'CAN':<11} {'samples':>8} {'rate Hz':>8} {'lost':>5} {'gaps':>5} {'|Δt−1ms| p99 ms':>16} {'max ms':>8}"
    print(header)
    for name, collector in collectors.items():
        stamps = np.array(collector.stamps)
        rate = (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 1 else 0.0
        jitter = np.abs(np.diff(stamps) - 1e-3) * 1e3 if len(stamps) > 1 else np.array([np.nan])
        lost = after[name]["lost_samples"] - before[name]["lost_samples"]
        gaps = after[name]["gaps"] - before[name]["gaps"]
        print(f"{name:<11} {len(stamps):>8} {rate:>8.1f} {lost:>5} {gaps:>5} {np.percentile(jitter, 99):>16.3f} "
              f"{jitter.max():>8.3f}")
        if collector.error:
            print(f"  {name}: feed error: {collector.error}")
        failed |= bool(collector.error) or lost > 0 or gaps > 0 or rate < 990 or np.percentile(jitter, 99) > 2.0
    written = cameras_after["frames_written"] - cameras_before["frames_written"]
    ahead = cameras_after["rendered_ahead"] - cameras_before["rendered_ahead"]
    print(f"cameras: {written} frame sets rendered, {ahead} of them ahead of their settled pose")
    for label, latencies in (("standalone", alone), ("in the cell", in_cell)):
        a = np.asarray(latencies) * 1e3
        print(f"moveL 10 mm ({SPEED} m/s, {ACCELERATION} m/s², ur_rtde, blocking) {label}: "
              f"median {np.median(a):.1f} ms, p95 {np.percentile(a, 95):.1f} ms, n {len(a)}")
    print("targets (RTDE ≥ 475/s and consistent; CAN 1 kHz, no gaps, jitter p99 ≤ 2 ms):",
          "NOT MET" if failed else "met")
    return 1 if failed else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of the loaded cell (default 60)")
    parser.add_argument("--burners", type=int, default=2, help="CPU burner processes (default 2)")
    parser.add_argument("--moves", type=int, default=30, help="moves of the standalone twin (default 30)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if not args.duration > 0 or args.burners < 0 or args.moves < 2:
        parser.error("--duration must be > 0, --burners ≥ 0, --moves ≥ 2")
    return run(args.duration, args.burners, args.moves, args.seed)


if __name__ == "__main__":
    sys.exit(main())
