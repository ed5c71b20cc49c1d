"""``python -m sim_devices.abb --host 127.0.0.3 [--port 80]``: run an IRC5 twin in the foreground.

Prints its endpoints as one JSON line, then serves until Ctrl-C or SIGTERM and stops cleanly.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading

from sim_devices.abb._twin import EGM_PORT, RWS_PORT, standalone_host


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim_devices.abb", description=__doc__.splitlines()[0])
    parser.add_argument("--host", default="127.0.0.2", help="loopback address to bind (default 127.0.0.2)")
    parser.add_argument("--port", type=int, default=RWS_PORT, help=f"RWS port (default {RWS_PORT})")
    parser.add_argument("--egm-port", type=int, default=EGM_PORT,
                        help=f"UDP port EGM packets go to on the host (default {EGM_PORT})")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--time-scale", type=float, default=1.0, help="simulated seconds per wall second")
    parser.add_argument("--truth", default=None, help="append the ground-truth log (JSON lines) here")
    parser.add_argument("--repeatability-um", type=float, default=None, help="σ per axis of the position error, µm")
    args = parser.parse_args(argv)
    extra = {"egm_remote_port": args.egm_port}
    if args.repeatability_um is not None:
        extra["repeatability_translation_std"] = args.repeatability_um * 1e-6
    try:
        twin = standalone_host(host=args.host, port=args.port, seed=args.seed, time_scale=args.time_scale,
                               truth_path=args.truth, **extra)
        endpoints = twin.start()
    except (OSError, ValueError) as exc:
        print(f"ABB twin: {exc}", file=sys.stderr)
        return 2
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    print(json.dumps(endpoints), flush=True)
    try:
        while not done.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        twin.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
