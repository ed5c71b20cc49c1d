"""Run twins in a child process, with endpoints handed back and a clean stop.

Some real clients (ur_rtde) hold the GIL while they wait for their server, so a twin must never
share a process with its client. ``TwinProcess`` starts a ``spawn`` child that builds a host object
from a factory, starts it, sends back its endpoints, then serves control calls until told to stop
(or until the parent goes away). It only ever stops the process it started.

A host object has ``start() -> dict`` (endpoints), ``stop() -> None`` and
``control(command: str, /, **kwargs) -> Any`` (the twin's control API: arm faults, read truth ...).

No child outlives its parent: the child stops its host when the control pipe reports end-of-file
(the parent's end closes with the parent, even on SIGKILL) or when its parent process id changes
(checked four times a second), and exits by force if stopping takes longer than ``STOP_GRACE``.
A child runs in a session of its own and ignores SIGINT (the parent decides when it stops), and
stops cleanly on SIGTERM.
"""

from __future__ import annotations

import importlib
import multiprocessing
import os
import signal
import threading
import time
import traceback
from multiprocessing.connection import Connection
from multiprocessing.connection import wait as wait_for_exits
from multiprocessing.context import SpawnProcess
from typing import Any

STOP_GRACE = 10.0  # s a child may take to stop its host once its parent is gone
TWIN_NICE = -5  # a twin's scheduling priority where the OS allows it (see _run_ahead_of_the_host)


class TwinProcessError(RuntimeError):
    """The twin process failed to start, died, or a control call failed inside it."""


class _ParentGone(BaseException):
    """Raised in the child's main thread when its parent is gone or SIGTERM asks it to stop."""


def _watch_parent(parent_pid: int, stopping: threading.Event) -> None:
    while not stopping.wait(0.25):
        if os.getppid() != parent_pid:
            os.kill(os.getpid(), signal.SIGTERM)  # interrupts the main thread's wait for a message
            return


def _hard_exit_later(seconds: float) -> None:
    timer = threading.Timer(seconds, lambda: os._exit(3))
    timer.daemon = True
    timer.start()


def _run_ahead_of_the_host(nice: int) -> None:
    """A twin stands for a device with a processor of its own, so where the OS lets it (root or
    CAP_SYS_NICE) its session's scheduling group and its threads get the weight of ``nice``
    (``TWIN_NICE`` unless the twin's owner says otherwise): a host busy on every core (a test run, an
    engine analysing, CPU burners) then delays the twin's answers and its 500 Hz cycle about as
    little as it would a real device's. Elsewhere nothing changes."""
    try:
        with open("/proc/self/autogroup", "w", encoding="ascii") as autogroup:  # Linux's per-session group
            autogroup.write(str(nice))
    except OSError:
        pass
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)  # this thread; threads started later inherit it
    except OSError:
        pass


def _child_main(factory_path: str, kwargs: dict[str, Any], conn: Connection, parent_pid: int, nice: int) -> None:
    # A twin is a device of its own: its own session, so a terminal's signals do not reach it and,
    # with the kernel's autogroup scheduling, busy processes of another session (a test run, a CPU
    # burner) share the CPU with it as one group instead of crowding it out thread by thread.
    os.setsid()
    _run_ahead_of_the_host(nice)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # The parent marks us daemonic (it terminates us if it exits without stopping us), and
    # multiprocessing refuses children to daemonic processes. A host may run twin processes of its
    # own (the cell supervisor); their lifetime is bound to ours by the pipe and parent watch below.
    multiprocessing.current_process().daemon = False

    def on_sigterm(*_: object) -> None:
        raise _ParentGone()

    signal.signal(signal.SIGTERM, on_sigterm)
    stopping = threading.Event()
    threading.Thread(target=_watch_parent, args=(parent_pid, stopping), name="parent-watch", daemon=True).start()
    host = None
    try:
        module_name, _, attr = factory_path.partition(":")
        factory = getattr(importlib.import_module(module_name), attr)
        host = factory(**kwargs)
        endpoints = host.start()
        conn.send({"ok": True, "endpoints": endpoints})
    except _ParentGone:
        _hard_exit_later(STOP_GRACE)
        if host is not None:
            host.stop()
        return
    except BaseException as exc:  # report any start-up failure to the parent, then exit
        try:
            conn.send({"ok": False, "error": f"{type(exc).__name__}: {exc}", "trace": traceback.format_exc()})
        except (OSError, BrokenPipeError):
            pass
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
    except _ParentGone:
        pass
    finally:
        stopping.set()
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # one stop is enough
        _hard_exit_later(STOP_GRACE)
        host.stop()
        try:
            conn.send({"ok": True, "stopped": True})
        except (OSError, BrokenPipeError):
            pass


def _exit_code(process: SpawnProcess, timeout: float) -> int | None:
    """``process``'s exit code once it has ended within ``timeout`` s, else None.

    ``multiprocessing`` reaps a child in whichever thread asks first (``is_alive()`` from a status
    call, its own clean-up when another process starts); a thread whose ``waitpid`` comes second sees
    ECHILD and gets None for a child that has ended. The code is stored by the reaping thread a moment
    later, so an ended child's code is read again until it is there: never reported as unknown.
    """
    process.join(timeout)
    code = process.exitcode
    if code is None and process.sentinel in wait_for_exits([process.sentinel], 0):
        deadline = time.monotonic() + 2.0
        while code is None and time.monotonic() < deadline:
            time.sleep(0.002)
            code = process.exitcode
    return code


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
    name : str, optional
        How errors name the twin (default: the factory).

    Use as a context manager, or call ``start``/``stop`` (``launch`` then ``wait_started`` starts
    several processes in parallel).
    """

    def __init__(self, factory: str, kwargs: dict[str, Any] | None = None, *, start_timeout: float = 30.0,
                 call_timeout: float = 10.0, name: str | None = None, nice: int = TWIN_NICE) -> None:
        self.factory = factory
        self.nice = nice
        self.kwargs = dict(kwargs or {})
        self.start_timeout = start_timeout
        self.call_timeout = call_timeout
        self.name = name or f"twin {factory}"
        self.endpoints: dict[str, Any] = {}
        self.exitcode: int | None = None
        self._process: SpawnProcess | None = None
        self._conn: Connection | None = None
        self._stop_requested = False
        self._lock = threading.Lock()

    def start(self) -> dict[str, Any]:
        self.launch()
        return self.wait_started()

    def launch(self) -> None:
        """Start the child process (it builds and starts its host in the background)."""
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe()
        process = ctx.Process(target=_child_main, args=(self.factory, self.kwargs, child, os.getpid(), self.nice),
                              daemon=True)
        self._process = process
        # The child ignores SIGINT from its first instruction (an ignored signal stays ignored across
        # exec): a Ctrl-C to the terminal's process group during its start-up, before it has a session
        # of its own, must not print an import traceback from it. (Blocking SIGINT instead would keep
        # this process's Ctrl-C, but multiprocessing's spawn clears the child's signal mask; a Ctrl-C
        # in the few milliseconds of the spawn is lost here.)
        in_main = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if in_main else None
        try:
            process.start()
        finally:
            if in_main:
                signal.signal(signal.SIGINT, previous if previous is not None else signal.SIG_DFL)
        child.close()
        self._conn = parent

    def wait_started(self) -> dict[str, Any]:
        """Wait for the host's endpoints; stops the child and raises ``TwinProcessError`` if it fails."""
        parent = self._conn
        if parent is None:
            raise TwinProcessError(f"{self.name} was not launched")
        if not parent.poll(self.start_timeout):
            self.stop()
            raise TwinProcessError(f"{self.name} did not start within {self.start_timeout} s")
        try:
            reply = parent.recv()
        except EOFError:
            self.stop()
            raise TwinProcessError(f"{self.name} died during start-up") from None
        if not reply["ok"]:
            self.stop()
            raise TwinProcessError(f"{self.name} failed to start: {reply['error']}\n{reply.get('trace', '')}")
        self.endpoints = reply["endpoints"]
        return self.endpoints

    def call(self, command: str, /, timeout: float | None = None, **kwargs: Any) -> Any:
        """Run ``host.control(command, **kwargs)`` in the child and return its result.

        ``command`` is positional-only, so ``kwargs`` may hold a ``command`` of their own (the
        cell's ``device`` command forwards one to a twin). ``timeout`` (s) overrides ``call_timeout``.
        """
        with self._lock:
            if self._conn is None or self._process is None or not self._process.is_alive():
                raise TwinProcessError(f"{self.name} is not running")
            try:
                self._conn.send((command, kwargs))
                if not self._conn.poll(timeout or self.call_timeout):
                    raise TwinProcessError(f"{self.name}: control call {command!r} timed out")
                reply = self._conn.recv()
            except (EOFError, OSError):
                raise TwinProcessError(f"{self.name} went away during control call {command!r}") from None
        if not reply["ok"]:
            raise TwinProcessError(f"{self.name}: control call {command!r} failed: {reply['error']}")
        return reply["result"]

    def request_stop(self) -> None:
        """Ask the child to stop, without waiting (``stop()`` then waits): several children told
        first stop side by side."""
        # Not under the call lock, as stop() never was: a call in flight must not hold up a stop.
        process, conn = self._process, self._conn
        if conn is None or process is None or self._stop_requested:
            return
        try:
            if process.is_alive():
                conn.send("stop")
                self._stop_requested = True
        except (OSError, BrokenPipeError):
            pass

    def stop(self, timeout: float = 10.0) -> None:
        """Ask the child to stop its twins; terminate it (only it) if it does not exit in time."""
        self.request_stop()
        process, conn = self._process, self._conn
        self._process = self._conn = None
        self._stop_requested = False
        if process is None:
            return
        try:
            if conn is not None and process.is_alive():
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
        self.exitcode = _exit_code(process, 0.0)
        if conn is not None:
            conn.close()

    @property
    def alive(self) -> bool:
        return self._process is not None and self._process.is_alive()

    @property
    def pid(self) -> int | None:
        return None if self._process is None else self._process.pid

    @property
    def sentinel(self) -> int | None:
        """A file descriptor that becomes ready when the child ends (``multiprocessing.connection.wait``)."""
        return None if self._process is None else self._process.sentinel

    def poll_exit(self, timeout: float = 0.0) -> int | None:
        """The child's exit code if it has ended within ``timeout`` s (it is then reaped), else None."""
        if self._process is None:
            return self.exitcode
        self.exitcode = _exit_code(self._process, timeout)
        return self.exitcode

    def __enter__(self) -> TwinProcess:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
