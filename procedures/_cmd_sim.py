"""``instrument sim``: run the whole simulated cell in the foreground until Ctrl-C or SIGTERM."""

from __future__ import annotations

import json
import signal
import sys
import threading
from pathlib import Path
from typing import Any

import yaml

from procedures._cli_common import seconds_value, seed_value
from procedures._files import InputRefused, read_text_file


def register(subparsers) -> None:
    parser = subparsers.add_parser("sim", help="run the simulated cell (all twins) until Ctrl-C")
    parser.add_argument("--config", type=Path, help="cell YAML (sections: world, optics, robot, rotary_table, "
                                                    "interferometer; optional 'seed', 'time_scale')")
    parser.add_argument("--seed", type=seed_value, default=None, help="seed of every random stream (default 0)")
    parser.add_argument("--directory", type=Path, default=Path("sim_runs/cell"),
                        help="where frames, truth log and station.yaml go (default sim_runs/cell)")
    parser.add_argument("--time-scale", type=seconds_value, default=None, help="simulated time per wall second")
    parser.add_argument("--robot-host", default=None, help="loopback address for the UR twin (127.0.0.N)")
    parser.add_argument("--json", action="store_true", help="print the endpoints as one JSON line")
    parser.set_defaults(handler=run)


def run(args) -> int:
    from sim_devices.cell import CellHost

    config: dict[str, Any] = {}
    if args.config:
        try:
            config = yaml.safe_load(read_text_file(args.config, what="cell configuration")) or {}
        except (InputRefused, yaml.YAMLError, RecursionError) as exc:
            print(f"instrument sim: cannot read {args.config}: {exc}", file=sys.stderr)
            return 2
        if not isinstance(config, dict):
            print(f"instrument sim: {args.config}: expected a mapping at the top level", file=sys.stderr)
            return 2
    file_seed, file_time_scale = config.pop("seed", 0), config.pop("time_scale", 1.0)
    seed = args.seed if args.seed is not None else int(file_seed)
    time_scale = args.time_scale if args.time_scale is not None else float(file_time_scale)
    host = CellHost(str(args.directory), seed=seed, robot_host=args.robot_host, time_scale=time_scale, config=config)

    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        try:
            endpoints = host.start()
        except ValueError as exc:  # a bad setting in the cell configuration
            print(f"instrument sim: {args.config or 'configuration'}: {exc}", file=sys.stderr)
            return 2
        if args.json:
            print(json.dumps(endpoints), flush=True)
        else:
            print(f"simulated cell running (seed {seed}); station file: {endpoints['station']}", flush=True)
            for name, value in endpoints.items():
                print(f"  {name}: {value}", flush=True)
            print("Ctrl-C to stop.", flush=True)
        while not stop.wait(0.5):
            pass
    finally:
        host.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print("simulated cell stopped", file=sys.stderr)
    return 0
