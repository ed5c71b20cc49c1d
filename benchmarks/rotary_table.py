"""Round trips of the rotary-table adapters against the twin (median and p99, milliseconds).

Run: ``.venv/bin/python benchmarks/rotary_table.py [--n 500]``. Each figure is one ``position()``
call of the real driver over the real client library: Modbus TCP (through the fault proxy and
direct to the server), Modbus RTU over a pty pair and the relay, GCS ``POS?`` over a pty pair and
over TCP (through the fault proxy and direct). The ``open`` column is the first ``open()`` of each
adapter on a twin just powered on (servo on and the reference move) or, for later adapters on the
same twin, finding it ready.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.rotary_table import create
from sim_devices import World
from sim_devices.rotary_table import RotaryTableTwin


def _measure(table, n: int) -> tuple[float, float]:
    for _ in range(20):
        table.position()
    samples = []
    for _ in range(n):
        start = time.perf_counter()
        table.position()
        samples.append(time.perf_counter() - start)
    ms = np.array(samples) * 1e3
    return float(np.median(ms)), float(np.percentile(ms, 99))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--n", type=int, default=500)
    args = parser.parse_args()
    if args.n < 1:
        parser.error("--n must be at least 1")
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    twin = RotaryTableTwin(World(), {})
    endpoints = twin.start()
    try:
        cases = {
            "modbus_tcp (fault proxy)": {
                "adapter": "modbus_tcp",
                "host": "127.0.0.1",
                "port": endpoints["modbus_tcp_port"],
            },
            "modbus_tcp (direct)": {
                "adapter": "modbus_tcp",
                "host": "127.0.0.1",
                "port": endpoints["modbus_tcp_direct_port"],
            },
            "modbus_rtu (pty relay)": {"adapter": "modbus_rtu", "port": endpoints["modbus_rtu_port"]},
            "gcs_serial POS? (pty relay)": {"adapter": "gcs_serial", "port": endpoints["gcs_port"]},
            "gcs_tcp POS? (fault proxy)": {"adapter": "gcs_tcp", "host": "127.0.0.1",
                                           "port": endpoints["gcs_tcp_port"]},
            "gcs_tcp POS? (direct)": {"adapter": "gcs_tcp", "host": "127.0.0.1",
                                      "port": endpoints["gcs_tcp_direct_port"]},
        }
        print(f"{'adapter':32s} {'open ms':>10s} {'median ms':>10s} {'p99 ms':>10s}   (n={args.n})")
        for label, config in cases.items():
            table = create(config, name="bench")
            started = time.perf_counter()
            table.open()
            opened = (time.perf_counter() - started) * 1e3
            try:
                median, p99 = _measure(table, args.n)
            finally:
                table.close()
            print(f"{label:32s} {opened:10.1f} {median:10.3f} {p99:10.3f}")
    finally:
        twin.stop()


if __name__ == "__main__":
    main()
