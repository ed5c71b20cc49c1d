"""A device client in an isolated worker process, and deadline-bound calls into it.

``WorkerLink`` starts a Python script in its own process (its own session, so a terminal's Ctrl-C
goes to the engine alone), hands it one end of a pipe, and sends it ``(id, method, args)``
requests. A reader thread routes the replies to the waiting callers, so calls from several
threads (a move on one, ``stop()`` on another) are in flight together. Every call has a deadline:
when it passes, or when the worker dies (a client crash, SIGKILL), the caller gets a typed error
at once and the worker is killed and reaped. Waiting is interruptible, so Ctrl-C and SIGTERM
handlers of the engine always run. A link that is collected, or still open when the interpreter
exits, shuts its pipe down so that the worker ends itself (stopping a move in progress), and is
killed if it does not within ``EXIT_WAIT``; a worker whose engine dies sees the same end of file.
"""

from __future__ import annotations

import contextlib
import itertools
import multiprocessing
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import weakref
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from drivers._errors import DeviceConnectionError, DeviceError, DeviceTimeout

WORKER_START_TIMEOUT = 10.0  # s for the worker's interpreter to start and greet (a loaded 2-core machine)
EXIT_WAIT = 2.0  # s a closed worker gets to exit by itself before it is killed


class WorkerFailure(Exception):
    """A typed failure reported by the worker: ``kind``, ``operation``, ``cause``, ``broken``."""

    def __init__(self, kind: str, operation: str, cause: str, broken: bool) -> None:
        super().__init__(f"{kind}: {operation}: {cause}")
        self.kind, self.operation, self.cause, self.broken = kind, operation, cause, broken


@dataclass
class _Shared:
    """What the reader thread and the callers share (not the link itself, so that the link can be
    collected while its reader still blocks on the pipe)."""

    condition: threading.Condition = field(default_factory=threading.Condition)
    replies: dict[int, tuple] = field(default_factory=dict)
    waiting: set[int] = field(default_factory=set)
    death: str | None = None  # why the worker is gone, once it is


class WorkerLink:
    """One worker process running ``script`` and the calls into it.

    Parameters
    ----------
    device : str
        Device name used in every error.
    script : Path
        The worker script; it is run as ``python -P script FD PARENT_PID`` and must first send
        ``(0, "ok", pid)``, then answer requests (see ``drivers.robot._ur_worker``).
    """

    def __init__(self, device: str, script: Path) -> None:
        self.device = device
        self.script = script
        self._ids = itertools.count(1)
        # Re-entrant: a signal handler may make a call (``stop()``) while this thread is sending. A
        # message is one write, so the handler's lands before or after it, never inside.
        self._send_lock = threading.RLock()
        self._shared = _Shared()
        self._process: subprocess.Popen | None = None
        self._conn: Connection | None = None
        self._finalizer: weakref.finalize | None = None

    # ----------------------------------------------------------------------------- life cycle
    def start(self) -> None:
        """Start the worker and wait (bounded) for its greeting."""
        parent_end, child_end = multiprocessing.Pipe(duplex=True)
        fd = child_end.fileno()
        try:
            process = subprocess.Popen(
                [sys.executable, "-P", str(self.script), str(fd), str(os.getpid())],
                pass_fds=(fd,), stdin=subprocess.DEVNULL, stdout=_diagnostics_fd(), start_new_session=True,
            )
        except OSError as exc:
            parent_end.close()
            raise DeviceConnectionError(self.device, "open", f"cannot start the client process: {exc}") from None
        finally:
            child_end.close()
        self._process, self._conn = process, parent_end
        # The finalizer's own handle on the pipe: it may shut the pipe down whatever the reader did.
        shutdown_handle = socket.socket(fileno=os.dup(parent_end.fileno()))
        self._finalizer = weakref.finalize(self, _end_worker, process, shutdown_handle, os.getpid())
        with self._shared.condition:
            self._shared.waiting.add(0)  # the greeting's id, before the reader can see it
        threading.Thread(target=_read_replies, args=(parent_end, process, self._shared),
                         name=f"{self.device}-replies", daemon=True).start()
        try:
            self._wait(0, "open", WORKER_START_TIMEOUT, "the client process did not start")
        except BaseException:
            self.kill()
            raise

    @property
    def pid(self) -> int | None:
        return None if self._process is None else self._process.pid

    @property
    def death(self) -> str | None:
        """Why the worker is gone (``"killed by SIGSEGV"``, ``"exited with code 1"``), or None."""
        return self._shared.death

    def kill(self) -> None:
        """SIGKILL to the worker (only it, by its id), then reap it; idempotent."""
        with self._shared.condition:
            self._shared.death = self._shared.death or "stopped by the engine"
            self._shared.condition.notify_all()
        if self._process is not None and self._process.poll() is None:
            with contextlib.suppress(OSError):
                self._process.kill()
        if self._finalizer is not None:
            self._finalizer()

    def close(self, deadline: float) -> None:
        """Ask the worker to disconnect its clients and exit; kill it if it takes longer."""
        try:
            if self._process is not None and self.death is None:
                with contextlib.suppress(DeviceError, WorkerFailure):
                    self.call("close", "close", (), deadline)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self._process.wait(EXIT_WAIT)
        finally:
            self.kill()

    # ----------------------------------------------------------------------------- calls
    def call(self, operation: str, method: str, args: tuple, deadline: float) -> Any:
        """The worker's result of ``method(*args)`` within ``deadline`` seconds.

        Raises
        ------
        WorkerFailure
            The typed failure the worker reported.
        DeviceTimeout
            No answer within the deadline (the worker is killed).
        DeviceConnectionError
            The worker is gone, or died during the call.
        """
        request_id = next(self._ids)
        shared = self._shared
        with shared.condition:
            if shared.death is not None:
                raise DeviceConnectionError(self.device, operation, f"the client process is gone ({shared.death})")
            shared.waiting.add(request_id)
        try:
            with self._send_lock:
                assert self._conn is not None
                self._conn.send((request_id, method, args))
        except (OSError, ValueError):  # the worker is gone: the reader thread is about to say why
            with shared.condition:
                shared.waiting.discard(request_id)
                shared.condition.wait_for(lambda: shared.death is not None, EXIT_WAIT + 1.0)
            raise DeviceConnectionError(self.device, operation,
                                        f"the client process died ({shared.death or 'pipe closed'})") from None
        reply = self._wait(request_id, operation, deadline, f"no answer within {deadline:.1f} s")
        if reply[1] == "ok":
            return reply[2]
        raise WorkerFailure(*reply[2:6])

    def _wait(self, request_id: int, operation: str, deadline: float, timeout_cause: str) -> tuple:
        shared = self._shared
        until = time.monotonic() + deadline
        reply = None
        try:
            with shared.condition:
                while reply is None:
                    reply = shared.replies.pop(request_id, None)
                    remaining = until - time.monotonic()
                    if reply is not None or remaining <= 0:
                        break
                    if shared.death is not None:
                        raise DeviceConnectionError(self.device, operation,
                                                    f"the client process died ({shared.death})")
                    shared.condition.wait(remaining)  # interruptible: a signal handler may raise here
        finally:
            with shared.condition:
                shared.waiting.discard(request_id)
                shared.replies.pop(request_id, None)
        if reply is None:
            self.kill()
            raise DeviceTimeout(self.device, operation, f"{timeout_cause}; the client process was stopped")
        return reply


def _read_replies(conn: Connection, process: subprocess.Popen, shared: _Shared) -> None:
    """Route replies to their callers until the pipe ends, then record why the worker is gone."""
    while True:
        try:
            reply = conn.recv()
        except (EOFError, OSError):
            break
        with shared.condition:
            if reply[0] in shared.waiting:
                shared.replies[reply[0]] = reply
                shared.condition.notify_all()
    try:
        code = process.wait(EXIT_WAIT)
    except subprocess.TimeoutExpired:  # closed its end of the pipe but lives on: not ours to keep
        process.kill()
        code = process.wait()
    with shared.condition:
        if shared.death is None:
            shared.death = _describe_exit(code)
        shared.condition.notify_all()
    conn.close()


def _end_worker(process: subprocess.Popen, pipe: socket.socket, owner_pid: int) -> None:
    """Shut the pipe down (the worker reads its end of file, stops a move and exits), wait for it
    ``EXIT_WAIT`` seconds, then SIGKILL it (by its own id, never a group) and reap it. The reader
    thread sees the end of file too and closes the parent's end. Only the process that started the
    worker does this, not a forked child that inherited the link."""
    if os.getpid() != owner_pid:
        return
    try:
        if process.poll() is None:
            with contextlib.suppress(OSError):
                pipe.shutdown(socket.SHUT_RDWR)  # unlike close(), wakes threads blocked on the pipe
            try:
                process.wait(EXIT_WAIT)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(OSError):
                    process.kill()
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(EXIT_WAIT)
    finally:
        pipe.close()


def _describe_exit(code: int) -> str:
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exited with code {code}"


def _diagnostics_fd() -> int:
    """Where the client library's console lines go: the engine's stderr, never its stdout (which may
    carry machine-readable output such as ``--jsonl``)."""
    try:
        os.fstat(2)
        return 2
    except OSError:
        return subprocess.DEVNULL
