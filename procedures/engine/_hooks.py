"""Hooks: tell the robot cell (or anything else) what a run is doing, off the step loop.

A hook is a Python callable (``module:function`` or an entry point in group
``opr_instrument.hooks``), a shell command (event JSON on stdin and in ``$INSTRUMENT_EVENT``) or an
HTTP POST to a loopback URL. ``HookRunner.emit`` only puts the event on each subscribed hook's
bounded queue; one worker thread per hook delivers them in order, so a slow or hanging hook never
holds up a motion. Every call has a **total** deadline (``timeout_s``):

- callable: run in a daemon thread, abandoned at the deadline (at most ``MAX_ABANDONED`` such
  threads per hook; after that its events are logged as undelivered instead of piling up threads);
- shell: its own session and process group, stdin/stderr through temporary files (a command that
  leaves a background child holding a pipe cannot block us), and a new marker per call in
  ``$INSTRUMENT_HOOK_ID`` that every descendant inherits. At the deadline the group and every process
  carrying the marker (found in ``/proc/*/environ``, however it left the group: ``setsid``, a double
  fork) get SIGTERM, SIGKILL after ``TERM_GRACE_S``; the shell is reaped within ``KILL_WAIT_S``. What a
  shell that returned left behind may run until the call's deadline, then is stopped the same way.
  ``close`` (the run's end) stops every process its shell hooks still run, and so does the process's
  exit (``atexit``), so no hook process outlives its run;
- http: no proxy, no redirects (a 3xx is a failure), the socket shut down at the deadline however
  slowly the server trickles, at most ``MAX_RESPONSE_BYTES`` of the answer read.

A failure is reported (``take_failures``; the engine logs each as a ``hook_failed`` event), never
raised. ``close`` waits at most the longest deadline for the queues to drain and reports every
event it could not deliver, so nothing is lost silently.
"""

from __future__ import annotations

import atexit
import http.client
import importlib
import importlib.metadata
import json
import os
import queue
import signal
import socket
import subprocess
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterable
from typing import Any
from urllib.parse import urlparse

from procedures.station import HookSpec

ENTRY_POINT_GROUP = "opr_instrument.hooks"
QUEUE_CAPACITY = 1000  # events waiting per hook; more are logged as undelivered
MAX_ABANDONED = 4  # callable calls still running past their deadline, per hook
MAX_RESPONSE_BYTES = 64 * 1024
KILL_WAIT_S = 2.0  # after SIGKILL to a shell hook's group, how long its shell may take to be reaped
TERM_GRACE_S = 1.0  # after SIGTERM to a shell hook's processes, how long they have before SIGKILL
HOOK_ID_VARIABLE = "INSTRUMENT_HOOK_ID"  # in a shell hook's environment: the call's marker, inherited by descendants


class HookFailed(RuntimeError):
    """One hook call did not succeed (the message says why)."""


def describe(spec: HookSpec) -> str:
    """The hook as the operator wrote it (for messages)."""
    return str(spec.call or spec.entry_point or spec.shell or spec.http)


# ----------------------------------------------------------------------------------- one call
def _resolve_callable(spec: HookSpec) -> Callable[[dict], Any]:
    if spec.call:
        module_name, _, attr = spec.call.partition(":")
        target: Any = importlib.import_module(module_name)
        for part in attr.split("."):
            target = getattr(target, part)
        return target
    found = importlib.metadata.entry_points(group=ENTRY_POINT_GROUP, name=spec.entry_point or "")
    if not found:
        raise HookFailed(f"no entry point {spec.entry_point!r} in group {ENTRY_POINT_GROUP!r}")
    return next(iter(found)).load()


class _CallableHook:
    """A Python callable in a daemon thread per call, abandoned at the deadline."""

    def __init__(self, spec: HookSpec) -> None:
        self.spec = spec
        self._running: list[threading.Thread] = []

    def __call__(self, event: dict) -> None:
        self._running = [thread for thread in self._running if thread.is_alive()]
        if len(self._running) >= MAX_ABANDONED:
            raise HookFailed(f"not called: {len(self._running)} earlier calls still running past their deadline")
        outcome: dict[str, BaseException] = {}

        def target() -> None:
            try:
                _resolve_callable(self.spec)(event)
            except BaseException as exc:  # reported to the caller below
                outcome["error"] = exc

        thread = threading.Thread(target=target, name=f"hook {describe(self.spec)}", daemon=True)
        thread.start()
        thread.join(self.spec.timeout_s)
        if thread.is_alive():
            self._running.append(thread)
            raise HookFailed(f"did not return within {self.spec.timeout_s} s (abandoned)")
        if "error" in outcome:
            exc = outcome["error"]
            raise HookFailed(f"{type(exc).__name__}: {exc}")


def _marked(marker: str) -> list[int]:
    """The processes whose environment carries ``HOOK_ID_VARIABLE=marker`` (a zombie's reads as empty)."""
    needle = f"{HOOK_ID_VARIABLE}={marker}".encode()
    found: list[int] = []
    try:
        names = os.listdir("/proc")
    except OSError:  # no /proc: only the process group is known
        return found
    for name in names:
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/environ", "rb") as environ:
                if needle in environ.read().split(b"\0"):
                    found.append(int(name))
        except OSError:  # gone, or not ours to read (then not ours to signal either)
            continue
    return found


def stop_hook_processes(marker: str, group: int | None = None, grace_s: float = TERM_GRACE_S) -> list[int]:
    """Stop what one shell hook call started: its process ``group`` (when its shell is not yet reaped) and
    every process carrying its marker, wherever it moved (``setsid``, a double fork). SIGTERM first,
    SIGKILL to what is left after ``grace_s``, again until nothing carries the marker (a process forked
    meanwhile). Returns the process ids signalled (for tests and messages)."""
    signalled: set[int] = set()

    def send(sig: signal.Signals) -> list[int]:
        pids = _marked(marker)
        if group is not None:
            try:
                os.killpg(group, sig)
            except (ProcessLookupError, PermissionError):
                pass
        for pid in pids:
            try:
                os.kill(pid, sig)
            except (ProcessLookupError, PermissionError):
                pass
        signalled.update(pids)
        return pids

    def gone() -> bool:
        # Twice, 50 ms apart: a process between fork and exec (``setsid`` forks) or in the middle of its
        # exec can read as carrying nothing for a moment, and a single empty look let it escape.
        if _marked(marker):
            return False
        time.sleep(0.05)
        return not _marked(marker)

    if not send(signal.SIGTERM) and group is None and gone():
        return []
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline and _marked(marker):
        time.sleep(0.02)
    for _ in range(20):
        send(signal.SIGKILL)
        time.sleep(0.02)
        if gone():
            break
        group = None  # killed once; what still carries the marker is found by it
    return sorted(signalled)


class _ShellCall:
    """One shell hook call whose processes may still run: its shell, or what the shell left behind."""

    def __init__(self, owner: object, marker: str, process: subprocess.Popen) -> None:
        self.owner = owner
        self.marker = marker
        self.process = process
        self.pid = os.getpid()  # the process that started it: a forked child never stops its parent's hooks
        self.timer: threading.Timer | None = None
        self._lock = threading.Lock()
        self.stopped = False

    def stop(self) -> None:
        with self._lock:
            if self.stopped:
                return
            self.stopped = True
        if self.timer is not None:
            self.timer.cancel()
        group = self.process.pid if self.process.returncode is None else None  # a reaped shell's id may be reused
        stop_hook_processes(self.marker, group)
        with _LIVE_LOCK:
            _LIVE.pop(self.marker, None)


_LIVE: dict[str, _ShellCall] = {}  # marker -> a call with processes that may still run
_LIVE_LOCK = threading.Lock()


def stop_shell_hooks(owner: object | None = None) -> None:
    """Stop every shell hook call still running or with processes left behind (of ``owner``, or all)."""
    with _LIVE_LOCK:
        calls = [call for call in _LIVE.values()
                 if (owner is None or call.owner is owner) and call.pid == os.getpid()]
    for call in calls:
        call.stop()


atexit.register(stop_shell_hooks)  # a process that ends with hooks still running takes them with it


def run_shell(spec: HookSpec, command: str, event: dict, owner: object | None = None) -> None:
    """Run one shell hook within its deadline (see the module docstring)."""
    payload = json.dumps(event)
    marker = uuid.uuid4().hex
    env = {**os.environ, "INSTRUMENT_EVENT": payload, "INSTRUMENT_EVENT_NAME": str(event.get("event")),
           HOOK_ID_VARIABLE: marker}
    deadline = time.monotonic() + spec.timeout_s
    with tempfile.TemporaryFile() as stdin, tempfile.TemporaryFile() as stderr:
        stdin.write(payload.encode())
        stdin.seek(0)
        # Files, not pipes: a background child that inherits them cannot keep us waiting for EOF.
        with _LIVE_LOCK:
            process = subprocess.Popen(command, shell=True, stdin=stdin, stdout=subprocess.DEVNULL, stderr=stderr,
                                       env=env, start_new_session=True)
            call = _LIVE[marker] = _ShellCall(owner, marker, process)
        try:
            status = process.wait(timeout=spec.timeout_s)
        except subprocess.TimeoutExpired:
            call.stop()  # the whole group (the shell and what it started) and whatever carries the marker
            try:
                process.wait(timeout=KILL_WAIT_S)
            except subprocess.TimeoutExpired:
                pass  # a zombie we cannot reap now; the OS reaps it with us
            raise HookFailed(f"shell command did not finish within {spec.timeout_s} s (its process group and "
                             "descendants stopped)") from None
        if call.stopped:  # stopped from outside (the run ended) while it ran
            raise HookFailed("shell command stopped: the run ended while it ran")
        if _marked(marker):  # it left processes behind: they may run until the call's deadline, not beyond
            call.timer = threading.Timer(max(0.0, deadline - time.monotonic()), call.stop)
            call.timer.daemon = True
            call.timer.start()
        else:
            with _LIVE_LOCK:
                _LIVE.pop(marker, None)
        if status != 0:
            stderr.seek(0)
            tail = stderr.read()[-300:].decode(errors="replace").strip()
            raise HookFailed(f"shell command exited with status {status}" + (f": {tail}" if tail else ""))


def _shutdown(connection: http.client.HTTPConnection, expired: threading.Event) -> None:
    expired.set()
    sock = connection.sock
    if sock is not None:
        try:
            sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass


def run_http(spec: HookSpec, url: str, event: dict) -> None:
    """POST ``event`` to ``url`` within the hook's total deadline (see the module docstring)."""
    parsed = urlparse(url)
    host = "127.0.0.1" if parsed.hostname == "localhost" else str(parsed.hostname)  # never a resolver's answer
    path = (parsed.path or "/") + (f"?{parsed.query}" if parsed.query else "")
    body = json.dumps(event).encode()
    deadline = time.monotonic() + spec.timeout_s
    connection = http.client.HTTPConnection(host, parsed.port or 80, timeout=spec.timeout_s)
    # The socket's timeout bounds each read; this timer bounds the whole exchange (a shut-down
    # socket reads as the end of the answer, so whether it fired is checked at the end too).
    expired = threading.Event()
    timer = threading.Timer(spec.timeout_s, _shutdown, args=(connection, expired))
    timer.daemon = True
    timer.start()
    try:
        connection.request("POST", path, body=body, headers={"Content-Type": "application/json"})
        response = connection.getresponse()
        if 300 <= response.status < 400:
            raise HookFailed(f"HTTP {response.status} from {url}: redirect to "
                             f"{response.getheader('Location')!r} not followed (hooks never follow redirects)")
        received = 0
        while received <= MAX_RESPONSE_BYTES:
            chunk = response.read1(MAX_RESPONSE_BYTES + 1 - received)
            if not chunk:
                break
            received += len(chunk)
        if expired.is_set():
            raise OSError("deadline")
        if received > MAX_RESPONSE_BYTES:
            raise HookFailed(f"answer from {url} longer than {MAX_RESPONSE_BYTES} bytes: not read further")
        if response.status >= 400:
            raise HookFailed(f"HTTP {response.status} from {url}")
    except (OSError, http.client.HTTPException) as exc:
        if expired.is_set() or time.monotonic() >= deadline - 0.01:
            raise HookFailed(f"POST {url}: no complete answer within {spec.timeout_s} s (connection closed)") \
                from None
        raise HookFailed(f"POST {url} failed: {type(exc).__name__}: {exc}") from None
    finally:
        timer.cancel()
        connection.close()


class _ShellHook:
    """A shell command per call; ``stop`` ends what its calls still run (see ``run_shell``)."""

    def __init__(self, spec: HookSpec, command: str) -> None:
        self.spec = spec
        self.command = command

    def __call__(self, event: dict) -> None:
        run_shell(self.spec, self.command, event, owner=self)

    def stop(self) -> None:
        stop_shell_hooks(owner=self)


def _caller(spec: HookSpec) -> Callable[[dict], None]:
    if spec.shell:
        return _ShellHook(spec, spec.shell)
    if spec.http:
        url = spec.http
        return lambda event: run_http(spec, url, event)
    return _CallableHook(spec)


# --------------------------------------------------------------------------- queue and worker
_STOP = object()


class _HookWorker:
    """One hook's queue and the thread that delivers its events in order."""

    def __init__(self, spec: HookSpec, report: Callable[[str, dict], None]) -> None:
        self.spec = spec
        self.call = _caller(spec)
        self.report = report
        self.queue: queue.Queue[Any] = queue.Queue(maxsize=QUEUE_CAPACITY)
        self.current: dict | None = None  # the event being delivered
        self.closed = False  # stop() has given up on the worker; it reports nothing more
        self.thread = threading.Thread(target=self._run, name=f"hooks: {describe(spec)}", daemon=True)
        self.thread.start()

    def submit(self, event: dict) -> None:
        try:
            self.queue.put_nowait(event)
        except queue.Full:
            self.report(f"hook {describe(self.spec)!r} on {event.get('event')}: not delivered: "
                        f"{QUEUE_CAPACITY} earlier events still waiting", event)

    def _run(self) -> None:
        while True:
            event = self.queue.get()
            if event is _STOP:
                return
            self.current = event
            try:
                self.call(event)
            except Exception as exc:  # a hook never stops the run
                if not self.closed:
                    self.report(f"hook {describe(self.spec)!r} on {event.get('event')}: {exc}", event)
            finally:
                self.current = None

    def stop(self, deadline: float) -> None:
        """Let the thread finish what is queued until ``deadline`` (monotonic); report the rest."""
        try:
            self.queue.put(_STOP, timeout=max(0.0, deadline - time.monotonic()))
        except queue.Full:
            pass
        self.thread.join(max(0.0, deadline - time.monotonic()))
        while True:  # whatever is still queued will not be delivered: say so, event by event
            try:
                event = self.queue.get_nowait()
            except queue.Empty:
                break
            if event is not _STOP:
                self.report(f"hook {describe(self.spec)!r} on {event.get('event')}: not delivered: "
                            "the run ended while earlier calls were still waiting", event)
        if self.thread.is_alive():
            self.closed = True
            current = self.current
            if current is not None:
                outcome = ("its processes stopped" if isinstance(self.call, _ShellHook)
                           else "its outcome is unknown")
                self.report(f"hook {describe(self.spec)!r} on {current.get('event')}: still running when the run "
                            f"ended; {outcome}", current)
            self.queue.put_nowait(_STOP)  # room was made above; the thread ends after its current call
        if isinstance(self.call, _ShellHook):  # the run is over: no shell hook process outlives it
            self.call.stop()


class HookRunner:
    """Runs the hooks of a station and a procedure at each event, off the caller's thread.

    Parameters
    ----------
    hooks : iterable of HookSpec
    on_failure : callable(message, event), optional
        Told about each failing or undelivered call, from the hook's worker thread. The messages
        are also kept for ``take_failures`` (what the engine logs, from its own thread).
    """

    def __init__(self, hooks: Iterable[HookSpec] = (), on_failure: Callable[[str, dict], None] | None = None) -> None:
        self.hooks = list(hooks)
        self.on_failure = on_failure
        self._failures: queue.SimpleQueue[str] = queue.SimpleQueue()
        self._workers: list[_HookWorker] | None = None
        self._lock = threading.Lock()

    def _report(self, message: str, event: dict) -> None:
        self._failures.put(message)
        if self.on_failure is not None:
            try:
                self.on_failure(message, event)
            except Exception:
                pass

    def emit(self, event: dict) -> None:
        """Queue ``event`` for every hook subscribed to ``event["event"]``; returns at once."""
        with self._lock:
            if self._workers is None:
                self._workers = [_HookWorker(spec, self._report) for spec in self.hooks]
            for worker in self._workers:
                if event["event"] in worker.spec.events:
                    worker.submit(event)

    def call(self, event: dict) -> list[str]:
        """Run every subscribed hook on ``event`` now, in this thread, each within its deadline;
        returns the failure messages (for scripts and tests; the engine uses ``emit``)."""
        failures = []
        for spec in self.hooks:
            if event["event"] not in spec.events:
                continue
            try:
                _caller(spec)(event)
            except Exception as exc:
                failures.append(f"hook {describe(spec)!r} on {event['event']}: {exc}")
        return failures

    def take_failures(self) -> list[str]:
        """The failure messages reported since the last call, oldest first."""
        messages = []
        while True:
            try:
                messages.append(self._failures.get_nowait())
            except queue.Empty:
                return messages

    def close(self, grace_s: float | None = None) -> None:
        """Deliver what is queued within ``grace_s`` (default: the longest hook deadline + 1 s) and
        stop the workers; every event left undelivered is reported. ``emit`` starts them again."""
        with self._lock:
            workers, self._workers = self._workers or [], None
        if not workers:
            return
        grace = grace_s if grace_s is not None else max(w.spec.timeout_s for w in workers) + 1.0
        deadline = time.monotonic() + grace
        for worker in workers:
            worker.stop(deadline)
