"""Run the web view (uvicorn) and, when asked, the OPC UA server, in one event loop until SIGINT or SIGTERM."""

from __future__ import annotations

import asyncio
import contextlib
import signal
import socket
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import uvicorn

from procedures.serve._app import WebSettings, create_app
from procedures.serve._launcher import RunLauncher
from procedures.serve._opcua import InstrumentOpcUa, OpcUaSettings
from procedures.serve._reader import StoreReader


class _Server(uvicorn.Server):
    """uvicorn without its own signal handling: it would re-raise SIGTERM after shutting down and so
    end the process before the OPC UA server and the run processes are stopped."""

    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        yield


@dataclass(frozen=True)
class ServeOptions:
    """host, port : the web view's address (port 0: a free one); opcua : the OPC UA server, or None."""

    web: WebSettings
    host: str = "127.0.0.1"
    port: int = 8000
    opcua: OpcUaSettings | None = None


def bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket (IPv4 or IPv6 after the address)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
        sock.listen(128)
    except OSError:
        sock.close()
        raise
    return sock


async def serve(options: ServeOptions, *, ready: Callable[[dict[str, Any]], None] = lambda endpoints: None) -> None:
    """Serve until SIGINT or SIGTERM (or cancellation); ``ready`` gets the bound addresses once all is up.

    On the way out every run process started over OPC UA is stopped (see ``RunLauncher.close``).
    """
    reader = StoreReader(options.web.runs_dir)
    sock = bind(options.host, options.port)
    app = create_app(options.web, reader=reader)
    server = _Server(uvicorn.Config(app, log_level="warning", timeout_graceful_shutdown=2, access_log=False))

    def shut_down() -> None:
        # The live pages' event streams never end by themselves: closed first, they let the graceful
        # shutdown finish, where uvicorn would cancel them after its timeout and log each traceback.
        app.state.watcher.close()
        server.should_exit = True

    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, shut_down)
    opcua = None
    try:
        if options.opcua is not None:
            opcua = InstrumentOpcUa(reader, RunLauncher(options.web.runs_dir), options.opcua)
            await opcua.start()
        web_task = asyncio.create_task(server.serve(sockets=[sock]))
        while not server.started and not web_task.done():
            await asyncio.sleep(0.05)
        if server.started:
            host, port = sock.getsockname()[:2]
            shown = f"[{host}]" if ":" in host else host
            ready({"web": f"http://{shown}:{port}/", "opcua": opcua.endpoint if opcua else None})
        await web_task
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
        if opcua is not None:
            await opcua.stop()
        sock.close()
        reader.close()
