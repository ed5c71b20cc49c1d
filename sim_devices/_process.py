"""Run twins in a child process, with endpoints handed back and a clean stop.

Some real clients (ur_rtde) hold the GIL while they wait for their server, so a twin must never
share a process with its client. ``TwinProcess`` starts a ``spawn`` child that builds a host object
from a factory, starts it, sends back its endpoints, then serves control calls until told to stop
(or until the parent goes away). It only ever stops the process it started.

A host object has ``start() -> dict`` (endpoints), ``stop() -> None`` and
``control(command: str, /, **kwargs) -> Any`` (the twin's control API: arm faults, read truth ...).
"""

from __future__ import annotations

import importlib
import multiprocessing
import threading
import traceback
from multiprocessing.connection import Connection
from multiprocessing.context import SpawnProcess
from typing import Any


class TwinProcessError(RuntimeError):
    """The twin process failed to start, died, or a control call failed inside it."""


def _child_main(factory_path: str, kwargs: dict[str, Any], conn: Connection) -> None:
    host = None
    try:
        module_name, _, attr = factory_path.partition(":")
        factory = getattr(importlib.import_module(module_name), attr)
        host = factory(**kwargs)
        endpoints = host.start()
        conn.send({"ok": True, "endpoints": endpoints})
    except BaseException as exc:  # report any start-up failure to the parent, then exit
        conn.send({"ok": False, "error": f"{type(exc).__name__}: {exc}", "trace": traceback.format_exc()})
        if host is not None:
            try:
                host.stop()
            except Exception:
                pass
        return
    try:
        while True:
            try:
                message = conn.recv()
            except (EOFError, OSError):
                break  # the parent went away: stop everything we started
            if message == "stop":
                break
            command, call_kwargs = message
            try:
                conn.send({"ok": True, "result": host.control(command, **call_kwargs)})
            except Exception as exc:
                conn.send({"ok": False, "error": f"{type(exc).__name__}: {exc}"})
    finally:
        host.stop()
        try:
            conn.send({"ok": True, "stopped": True})
        except (OSError, BrokenPipeError):
            pass


class TwinProcess:
    """A twin host in its own process.

    Parameters
    ----------
    factory : str
        ``"module:callable"`` returning a host object (see module docstring).
    kwargs : dict
        Keyword arguments for the factory (must be picklable).
    start_timeout, call_timeout : float
        Seconds to wait for start-up and for each control call.

    Use as a context manager, or call ``start``/``stop``.
    """

    def __init__(self, factory: str, kwargs: dict[str, Any] | None = None, *, start_timeout: float = 30.0,
                 call_timeout: float = 10.0) -> None:
        self.factory = factory
        self.kwargs = dict(kwargs or {})
        self.start_timeout = start_timeout
        self.call_timeout = call_timeout
        self.endpoints: dict[str, Any] = {}
        self._process: SpawnProcess | None = None
        self._conn: Connection | None = None
        self._lock = threading.Lock()

    def start(self) -> dict[str, Any]:
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe()
        process = ctx.Process(target=_child_main, args=(self.factory, self.kwargs, child), daemon=True)
        self._process = process
        process.start()
        child.close()
        self._conn = parent
        if not parent.poll(self.start_timeout):
            self.stop()
            raise TwinProcessError(f"twin {self.factory} did not start within {self.start_timeout} s")
        try:
            reply = parent.recv()
        except EOFError:
            self.stop()
            raise TwinProcessError(f"twin {self.factory} died during start-up") from None
        if not reply["ok"]:
            self.stop()
            raise TwinProcessError(f"twin {self.factory} failed to start: {reply['error']}\n{reply.get('trace', '')}")
        self.endpoints = reply["endpoints"]
        return self.endpoints

    def call(self, command: str, /, timeout: float | None = None, **kwargs: Any) -> Any:
        """Run ``host.control(command, **kwargs)`` in the child and return its result.

        ``command`` is positional-only, so ``kwargs`` may hold a ``command`` of their own (the
        cell's ``device`` command forwards one to a twin). ``timeout`` (s) overrides ``call_timeout``.
        """
        with self._lock:
            if self._conn is None or self._process is None or not self._process.is_alive():
                raise TwinProcessError(f"twin {self.factory} is not running")
            self._conn.send((command, kwargs))
            if not self._conn.poll(timeout or self.call_timeout):
                raise TwinProcessError(f"twin {self.factory}: control call {command!r} timed out")
            reply = self._conn.recv()
        if not reply["ok"]:
            raise TwinProcessError(f"twin {self.factory}: control call {command!r} failed: {reply['error']}")
        return reply["result"]

    def stop(self, timeout: float = 10.0) -> None:
        """Ask the child to stop its twins; terminate it (only it) if it does not exit in time."""
        process, conn = self._process, self._conn
        self._process = self._conn = None
        if process is None:
            return
        try:
            if conn is not None and process.is_alive():
                conn.send("stop")
                conn.poll(timeout)
        except (OSError, BrokenPipeError):
            pass
        process.join(timeout)
        if process.is_alive():
            process.terminate()
            process.join(5.0)
        if process.is_alive():
            process.kill()
            process.join(5.0)
        if conn is not None:
            conn.close()

    @property
    def alive(self) -> bool:
        return self._process is not None and self._process.is_alive()

    def __enter__(self) -> TwinProcess:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
