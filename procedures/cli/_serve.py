"""``instrument serve``: the live web view of the runs folder, and with ``--opcua`` the OPC UA server."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "serve", help="live web view of the runs (and an OPC UA server with --opcua)",
        description="Serve the web view of the run store: runs list, the live run, reports, robots. "
                    "Loopback only unless --allow-remote. Stops on Ctrl-C or SIGTERM (runs started over "
                    "OPC UA are aborted then). Exit codes: 0 stopped, 2 bad arguments or address in use.")
    parser.add_argument("--runs-dir", "--runs", dest="runs_dir", default=os.environ.get("INSTRUMENT_RUNS", "runs"),
                        help="runs folder with runs.sqlite (default: $INSTRUMENT_RUNS or ./runs; created if missing)")
    parser.add_argument("--store", default=None, metavar="URL",
                        help="a shared run store, postgresql://USER@HOST/DATABASE (default: $INSTRUMENT_STORE, else "
                             "the runs folder's runs.sqlite); frames and reports are read from the runs folder")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address of the web view (default 127.0.0.1; another than loopback needs --allow-remote)")
    parser.add_argument("--port", type=int, default=8000, help="web view port (default 8000; 0 picks a free one)")
    parser.add_argument("--allow-remote", action="store_true",
                        help="allow a non-loopback --host; every request must then carry the token")
    parser.add_argument("--token", default=os.environ.get("INSTRUMENT_SERVE_TOKEN"),
                        help="token every request must carry (default: $INSTRUMENT_SERVE_TOKEN; with --allow-remote "
                             "and no token, a random one is made and printed)")
    parser.add_argument("--opcua", action="store_true", help="also run the OPC UA server for the robot cell")
    parser.add_argument("--opcua-host", default="127.0.0.1",
                        help="OPC UA address (loopback only: the endpoint has no security; see docs/opcua.md)")
    parser.add_argument("--opcua-port", type=int, default=4840, help="OPC UA port (default 4840; 0 picks a free one)")
    parser.set_defaults(handler=run)


def _problem(message: str) -> int:
    print(f"instrument serve: {message}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    import asyncio

    from procedures.serve import OpcUaSettings, ServeOptions, WebSettings, is_loopback, new_token, serve

    loopback = is_loopback(args.host)
    if not loopback and not args.allow_remote:
        return _problem(f"--host {args.host} is not a loopback address; add --allow-remote (a token is then required)")
    if args.opcua and not is_loopback(args.opcua_host):
        return _problem(f"--opcua-host {args.opcua_host}: the OPC UA endpoint serves loopback only "
                        "(no security policy is configured; see docs/opcua.md)")
    for name, port in (("--port", args.port), ("--opcua-port", args.opcua_port)):
        if not 0 <= port <= 65535:
            return _problem(f"{name} {port}: expected 0..65535")
    if args.store is not None:
        from procedures.store import STORE_ENV, StoreError, store_location

        try:
            store_location(args.store)
        except StoreError as exc:
            return _problem(str(exc))
        # The readers, the OPC UA launcher and the runs it starts all open the store through this variable.
        os.environ[STORE_ENV] = args.store
    runs_dir = Path(args.runs_dir)
    if runs_dir.exists() and not runs_dir.is_dir():
        return _problem(f"--runs-dir {runs_dir}: not a folder")
    token = args.token
    if not loopback and not token:
        token = new_token()
        print(f"token (give it as ?token=... once, or Authorization: Bearer ...): {token}", file=sys.stderr)
    options = ServeOptions(web=WebSettings(runs_dir=runs_dir, token=token, loopback_only=loopback), host=args.host,
                           port=args.port,
                           opcua=OpcUaSettings(host=args.opcua_host, port=args.opcua_port) if args.opcua else None)

    def ready(endpoints: dict) -> None:
        print(f"web view: {endpoints['web']}", flush=True)
        if endpoints.get("opcua"):
            print(f"OPC UA: {endpoints['opcua']}", flush=True)
        print(f"runs folder: {runs_dir.resolve()} (Ctrl-C stops)", file=sys.stderr, flush=True)

    try:
        asyncio.run(serve(options, ready=ready))
    except OSError as exc:  # the address in use, or not ours to bind
        return _problem(f"cannot listen: {exc.strerror or exc}")
    return 0
