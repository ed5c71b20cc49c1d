"""A small control channel for a running simulated cell: JSON lines over loopback TCP.

The cell's twins live in their own process. Tests and the procedure engine (the simulated
"operator" who re-mounts the OPR or re-aims the interferometer) reach them through this channel:
one request line ``{"command": ..., "args": {...}}``, one reply line ``{"ok": true, "result": ...}``
or ``{"ok": false, "error": ...}``.
"""

from __future__ import annotations

import json
import socket
import socketserver
import threading
from collections.abc import Callable
from typing import Any


class ControlError(RuntimeError):
    """The cell refused or failed a control command, or could not be reached."""


class ControlServer:
    """Serve ``handler(command, **args)`` on ``host:port`` (port 0: the OS picks one)."""

    def __init__(self, handler: Callable[..., Any], host: str = "127.0.0.1", port: int = 0) -> None:
        if not host.startswith("127."):
            raise ValueError(f"control server binds loopback only, got {host!r}")
        outer = self

        class _Handler(socketserver.StreamRequestHandler):
            timeout = 30.0

            def handle(self) -> None:
                for raw in self.rfile:
                    try:
                        request = json.loads(raw)
                        result = outer._handler(request["command"], **dict(request.get("args") or {}))
                        reply = {"ok": True, "result": result}
                    except Exception as exc:  # the reply carries the error; the server keeps going
                        reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
                    self.wfile.write((json.dumps(reply, default=_default) + "\n").encode())

        class _Server(socketserver.ThreadingTCPServer):
            daemon_threads = True
            allow_reuse_address = True

        self._handler = handler
        self._server = _Server((host, port), _Handler)
        bound_host, bound_port = self._server.socket.getsockname()[:2]
        self.address: tuple[str, int] = (str(bound_host), int(bound_port))
        self._thread = threading.Thread(target=self._server.serve_forever, name="cell-control", daemon=True)

    def start(self) -> tuple[str, int]:
        self._thread.start()
        return self.address

    def stop(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(5.0)


class ControlClient:
    """Send control commands to a cell. One short connection per call (robust to cell restarts)."""

    def __init__(self, host: str, port: int, timeout: float = 30.0) -> None:
        self.host, self.port, self.timeout = host, int(port), timeout

    def call(self, command: str, **args: Any) -> Any:
        try:
            with socket.create_connection((self.host, self.port), timeout=self.timeout) as sock:
                sock.sendall((json.dumps({"command": command, "args": args}, default=_default) + "\n").encode())
                reply = sock.makefile("rb").readline()
        except OSError as exc:
            raise ControlError(f"simulated cell at {self.host}:{self.port}: {command} failed: {exc}") from exc
        if not reply:
            raise ControlError(f"simulated cell at {self.host}:{self.port}: {command}: connection closed")
        reply = json.loads(reply)
        if not reply["ok"]:
            raise ControlError(f"simulated cell: {command} failed: {reply['error']}")
        return reply["result"]


def _default(value: Any) -> Any:
    try:
        import numpy as np

        if isinstance(value, np.ndarray):
            return value.tolist()
        if isinstance(value, (np.floating, np.integer)):
            return value.item()
    except ImportError:  # pragma: no cover
        pass
    raise TypeError(f"cannot send {type(value).__name__} over the control channel")
