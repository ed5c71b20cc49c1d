"""A small control channel for a running simulated cell: JSON lines over loopback TCP.

The cell's twins live in their own process. Tests and the procedure engine (the simulated
"operator" who re-mounts the OPR or re-aims the interferometer) reach them through this channel:
one request line ``{"command": ..., "args": {...}}``, one reply line ``{"ok": true, "result": ...}``
or ``{"ok": false, "error": ...}``.

``dispatch`` is how a host object (the cell, a twin) turns a command name and its arguments into
a call of one of its typed methods, through one explicit table: an unknown command or arguments
that do not fit the method's signature are one clear ``ValueError``, never a ``TypeError`` from
deep inside.
"""

from __future__ import annotations

import inspect
import json
import socket
import socketserver
import threading
from collections.abc import Callable, Mapping
from typing import Any


class ControlError(RuntimeError):
    """The cell refused or failed a control command, or could not be reached."""


def dispatch(table: Mapping[str, Callable[..., Any]], command: str, args: Mapping[str, Any], what: str) -> Any:
    """Call ``table[command](**args)`` after checking the command and its arguments.

    Parameters
    ----------
    table : mapping
        Command name → the (bound) method that carries it out.
    command : str
        The command asked for.
    args : mapping
        Its keyword arguments.
    what : str
        Who answers, for the messages (``"simulated cell"``).

    Raises
    ------
    ValueError
        For an unknown command (naming the known ones) or arguments that do not fit the method
        (naming its signature). Errors raised by the method itself pass through unchanged.
    """
    method = table.get(command)
    if method is None:
        raise ValueError(f"{what}: unknown command {command!r}; expected one of {', '.join(sorted(table))}")
    signature = inspect.signature(method)
    try:
        signature.bind(**args)
    except TypeError as exc:
        # The parameter names and defaults say what is expected; the annotations would only add noise.
        plain = signature.replace(parameters=[p.replace(annotation=p.empty) for p in signature.parameters.values()],
                                  return_annotation=signature.empty)
        raise ValueError(f"{what}: bad arguments for {command}{plain}: {exc}") from None
    return method(**args)


class ControlServer:
    """Serve ``handler(command, /, **args)`` on ``host:port`` (port 0: the OS picks one).

    A request that is not a JSON object with a ``command`` string (and optionally an ``args``
    object) gets an error reply naming what is wrong; the connection stays usable.
    """

    def __init__(self, handler: Callable[..., Any], host: str = "127.0.0.1", port: int = 0) -> None:
        if not host.startswith("127."):
            raise ValueError(f"control server binds loopback only, got {host!r}")
        outer = self

        class _Handler(socketserver.StreamRequestHandler):
            timeout = 30.0

            def handle(self) -> None:
                for raw in self.rfile:
                    try:
                        command, args = _parse_request(raw)
                        result = outer._handler(command, **args)
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
        # A short poll: shutdown() waits for the loop to look at its flag (0.5 s by default, paid
        # at every cell stop).
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.05},
                                        name="cell-control", daemon=True)

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

    def call(self, command: str, /, **args: Any) -> Any:
        """Run ``command`` with keyword ``args`` in the cell and return its result.

        ``command`` is positional-only, so ``args`` may itself hold a ``command`` (the cell's
        ``device`` command forwards one to a twin).

        Raises
        ------
        ControlError
            The cell could not be reached, closed the connection, or refused or failed the command.
        """
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


def _parse_request(raw: bytes) -> tuple[str, dict[str, Any]]:
    """``(command, args)`` of one request line, or a ValueError saying what is wrong with it."""
    expected = 'expected {"command": "<name>", "args": {...}}'
    try:
        request = json.loads(raw)
    except ValueError as exc:
        raise ValueError(f"request is not JSON ({exc}); {expected}") from None
    if not isinstance(request, dict) or not isinstance(request.get("command"), str):
        raise ValueError(f"request has no command; {expected}")
    args = request.get("args") or {}
    if not isinstance(args, dict):
        raise ValueError(f"args of {request['command']!r} must be an object, got {type(args).__name__}")
    return request["command"], args


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
