"""Interferometer feed benchmark: rate, latency and lost samples over socketcand and slcan.

The twin runs in its own process (``TwinProcess``), as a real head would be another device; the
driver (``CanInterferometer`` on python-can) reads both transports at once in this process.

    .venv/bin/python benchmarks/interferometer.py                  # 60 s, both transports
    .venv/bin/python benchmarks/interferometer.py --duration 10 --transport slcan

Latency is the driver's receive time minus the frame's timestamp: for socketcand that timestamp
is the frame's receive time on the bus (the twin's real send time plus bus time and a kernel
latency, as socketcand forwards the kernel's), so it covers TCP, python-can and the driver; slcan
frames are stamped by python-can on the host when read, so there it only covers python-can →
driver. Jitter is |Δt − 1 ms| between consecutive samples' timestamps (socketcand: the twin's send
schedule as the bus saw it; slcan: python-can's read times). Target: 1 kHz with no lost samples for 60 s.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers import DeviceError
from drivers.interferometer import create
from sim_devices import TwinProcess


class Collector(threading.Thread):
    """Consumes every sample of one feed and keeps what the table needs."""

    def __init__(self, device, duration: float) -> None:
        super().__init__(name=f"collect {device.name}", daemon=True)
        self.device, self.duration = device, duration
        self.latency: list[float] = []
        self.stamps: list[float] = []
        self.arrivals: list[float] = []
        self.defects: list[str] = []
        self.error: str | None = None

    def run(self) -> None:
        end = time.monotonic() + self.duration
        try:
            for sample in self.device.samples(timeout=2.0):
                self.latency.append(sample.received - sample.timestamp)
                self.stamps.append(sample.timestamp)
                self.arrivals.append(sample.received)
                if sample.defect and len(self.stamps) > 1:
                    self.defects.append(sample.defect)
                if time.monotonic() >= end:
                    break
        except DeviceError as exc:
            self.error = str(exc)


def run(duration: float, transports: list[str], seed: int) -> int:
    with TwinProcess("sim_devices.interferometer:StandaloneInterferometerHost", {"seed": seed}) as twin:
        endpoints = twin.endpoints
        configs = {"socketcand": {"adapter": "socketcand", **endpoints["socketcand"]},
                   "slcan": {"adapter": "slcan", "port": endpoints["slcan"]["port"]}}
        devices = {name: create(configs[name], name=name) for name in transports}
        for device in devices.values():
            device.open()
        try:
            time.sleep(0.5)  # let the feeds settle (first frames, python-can buffers)
            before = {name: device.stats() for name, device in devices.items()}
            twin_before = twin.call("stats")
            collectors = {name: Collector(device, duration) for name, device in devices.items()}
            started = time.monotonic()
            for collector in collectors.values():
                collector.start()
            for collector in collectors.values():
                collector.join(duration + 10.0)
            elapsed = time.monotonic() - started
            after = {name: device.stats() for name, device in devices.items()}
            twin_after = twin.call("stats")
            period_hz = float(twin.call("endpoints")["layout"]["sample_rate"])
        finally:
            for device in devices.values():
                device.close()

    print(f"interferometer feed, {duration:.0f} s, transports {', '.join(transports)} (twin in its own process)")
    header = (f"{'transport':<11} {'samples':>8} {'rate Hz':>8} {'lost':>5} {'gaps':>5} {'stalls':>6} "
              f"{'proto err':>9} {'lat p50 ms':>10} {'lat p99 ms':>10} {'lat max ms':>10} {'intvl p99 ms':>12} "
              f"{'jit p50 ms':>10} {'jit p99 ms':>10} {'jit max ms':>10}")
    print(header)
    print("-" * len(header))
    failed = False
    for name, collector in collectors.items():
        count = len(collector.stamps)
        delta = {key: after[name][key] - before[name][key] for key in ("lost_samples", "gaps", "stalls",
                                                                        "protocol_errors")}
        span = collector.stamps[-1] - collector.stamps[0] if count > 1 else float("nan")
        rate = (count - 1) / span if count > 1 else 0.0
        latency = np.array(collector.latency) * 1e3
        clock = np.array(collector.stamps if name == "socketcand" else collector.arrivals)
        intervals = np.diff(clock) * 1e3 if count > 1 else np.array([np.nan])
        jitter = np.abs(np.diff(collector.stamps) * 1e3 - 1e3 / period_hz) if count > 1 else np.array([np.nan])
        print(f"{name:<11} {count:>8} {rate:>8.1f} {delta['lost_samples']:>5} {delta['gaps']:>5} "
              f"{delta['stalls']:>6} {delta['protocol_errors']:>9} {np.percentile(latency, 50):>10.3f} "
              f"{np.percentile(latency, 99):>10.3f} {latency.max():>10.3f} {np.percentile(intervals, 99):>12.3f} "
              f"{np.percentile(jitter, 50):>10.3f} {np.percentile(jitter, 99):>10.3f} {jitter.max():>10.3f}")
        if collector.error:
            print(f"  {name}: feed error: {collector.error}")
        for defect in collector.defects[:5]:
            print(f"  {name}: {defect}")
        failed |= bool(collector.error) or delta["lost_samples"] > 0 or delta["gaps"] > 0 or rate < 990
    produced = twin_after["produced"] - twin_before["produced"]
    print(f"twin: {produced} samples produced in {elapsed:.1f} s ({produced / elapsed:.1f} Hz), "
          f"late-skipped {twin_after['late_skipped'] - twin_before['late_skipped']}, "
          f"slcan overflows {twin_after['slcan_overflows'] - twin_before['slcan_overflows']}")
    print("interval column: frame timestamps for socketcand, host arrival times for slcan; "
          "jitter: |Δ timestamp − period|")
    print("target (1 kHz, no lost samples):", "NOT MET" if failed else "met")
    return 1 if failed else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of feed to measure (default 60)")
    parser.add_argument("--transport", choices=["socketcand", "slcan", "both"], default="both")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if not args.duration > 0:
        parser.error("--duration must be > 0")
    transports = ["socketcand", "slcan"] if args.transport == "both" else [args.transport]
    return run(args.duration, transports, args.seed)


if __name__ == "__main__":
    sys.exit(main())
