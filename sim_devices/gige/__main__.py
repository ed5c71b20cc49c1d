"""``python -m sim_devices.gige --host 127.0.0.N``: one twin camera, the OPR at the reference pose.

For Aravis's own tools (``arv-tool-0.8 -a 127.0.0.N``, ``arv-camera-test-0.8 -n 127.0.0.N``) and
hand checks. Runs in the foreground until Ctrl-C or SIGTERM; prints its endpoints once bound.
"""

from __future__ import annotations

import argparse
import json
import signal
import threading

from sim_devices.gige._host import GigeTwinHost


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim_devices.gige", description=__doc__.splitlines()[0])
    parser.add_argument("--host", required=True, help="the camera's address (127.0.0.0/8 unless --allow-remote)")
    parser.add_argument("--camera", choices=("x", "y", "z"), default="x", help="which screen it images (default x)")
    parser.add_argument("--seed", type=int, default=0, help="world seed: the optics and the noise (default 0)")
    parser.add_argument("--static", action="store_true", help="send one rendered frame for every trigger")
    parser.add_argument("--allow-remote", action="store_true", help="serve on an address outside loopback")
    args = parser.parse_args(argv)
    host = GigeTwinHost(args.host, camera={"camera": args.camera, "render": "static" if args.static else "pose"},
                        world={"seed": args.seed}, allow_remote=args.allow_remote)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        print(json.dumps(host.start()), flush=True)
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        host.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
