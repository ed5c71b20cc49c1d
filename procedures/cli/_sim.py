"""``instrument sim``: run the whole simulated cell in the foreground until Ctrl-C or SIGTERM."""

from __future__ import annotations

import json
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from procedures.cli._common import seconds_value, seed_value
from procedures.station import InputRefused, read_text_file


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "sim", help="run the simulated cell (all twins) until Ctrl-C",
        description="Start every twin of the simulated cell around one seeded world model and write a station "
                    "file for it; runs in the foreground until Ctrl-C or SIGTERM.",
        epilog="exit codes: 0 stopped, 2 bad cell configuration or arguments")
    parser.add_argument("--config", type=Path, help="cell YAML (sections: world, optics, robot, rotary_table, "
                                                    "interferometer; optional 'seed', 'time_scale')")
    parser.add_argument("--seed", type=seed_value, default=None, help="seed of every random stream (default 0)")
    parser.add_argument("--directory", type=Path, default=Path("sim_runs/cell"),
                        help="where frames, truth log and station.yaml go (default sim_runs/cell)")
    parser.add_argument("--time-scale", type=seconds_value, default=None, help="simulated time per wall second")
    parser.add_argument("--robot-host", default=None, help="loopback address for the UR twin (127.0.0.N)")
    parser.add_argument("--json", action="store_true",
                        help="print the endpoints as exactly one JSON line on stdout (for scripts)")
    parser.set_defaults(handler=run)


def run(args) -> int:
    import yaml

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
            for line in endpoint_lines(endpoints, seed=seed, time_scale=time_scale):
                print(line, flush=True)
        while not stop.wait(0.5):
            pass
    finally:
        host.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print("simulated cell stopped", file=sys.stderr)
    return 0


_TITLES = {"station": "station file", "truth_log": "truth log", "control": "control channel",
           "rotary_table": "rotary table"}


def endpoint_text(value: Any) -> str:
    """One endpoint as a person reads it: ``127.0.0.1:5020``, ``rtde 127.0.0.5:30004, dashboard …``."""
    if isinstance(value, dict):
        if set(value) >= {"host", "port"}:
            rest = {k: v for k, v in value.items() if k not in ("host", "port")}
            return f"{value['host']}:{value['port']}" + (f" ({endpoint_text(rest)})" if rest else "")
        return ", ".join(f"{key.replace('_', ' ')} {endpoint_text(item)}" for key, item in value.items())
    if isinstance(value, (list, tuple)):
        return ", ".join(endpoint_text(item) for item in value)
    return str(value)


def endpoint_lines(endpoints: dict[str, Any], *, seed: int, time_scale: float) -> list[str]:
    """What ``instrument sim`` prints once the cell runs: one aligned line per endpoint."""
    first = [key for key in ("station", "truth_log", "control") if key in endpoints]
    order = first + [key for key in endpoints if key not in first]
    titles = {key: _TITLES.get(key, key.replace("_", " ")) for key in order}
    width = max(len(title) for title in titles.values())
    lines = [f"simulated cell running (seed {seed}, time scale {time_scale:g}); Ctrl-C stops it"]
    lines += [f"  {titles[key]:<{width}}  {endpoint_text(endpoints[key])}" for key in order]
    lines.append(f"run a procedure on it: instrument run iso9283_repeatability --station {endpoints.get('station')}")
    return lines
