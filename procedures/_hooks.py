"""Hooks: tell the robot cell (or anything else) what a run is doing.

A hook is a Python callable (``module:function`` or an entry point in group
``opr_instrument.hooks``), a shell command (event JSON on stdin and in ``$INSTRUMENT_EVENT``) or an
HTTP POST to a loopback URL. Each has a timeout. A hook that fails, hangs or returns an error is
logged and otherwise ignored: hooks run after the sample is committed, so they can never lose data.
"""

from __future__ import annotations

import importlib
import json
import os
import signal
import subprocess
import threading
import urllib.error
import urllib.request
from collections.abc import Callable, Iterable
from importlib.metadata import entry_points
from typing import Any

from procedures._models import HookSpec

ENTRY_POINT_GROUP = "opr_instrument.hooks"


class HookFailed(RuntimeError):
    pass


def _resolve_callable(spec: HookSpec) -> Callable[[dict], Any]:
    if spec.call:
        module_name, _, attr = spec.call.partition(":")
        target: Any = importlib.import_module(module_name)
        for part in attr.split("."):
            target = getattr(target, part)
        return target
    found = entry_points(group=ENTRY_POINT_GROUP, name=spec.entry_point or "")
    if not found:
        raise HookFailed(f"no entry point {spec.entry_point!r} in group {ENTRY_POINT_GROUP!r}")
    return next(iter(found)).load()


def _run_callable(spec: HookSpec, event: dict) -> None:
    outcome: dict[str, BaseException] = {}

    def target() -> None:
        try:
            _resolve_callable(spec)(event)
        except BaseException as exc:  # reported to the caller below
            outcome["error"] = exc

    # A daemon thread: a hook that hangs is abandoned at its timeout, never waited for.
    thread = threading.Thread(target=target, name=f"hook {spec.call or spec.entry_point}", daemon=True)
    thread.start()
    thread.join(spec.timeout_s)
    if thread.is_alive():
        raise HookFailed(f"did not return within {spec.timeout_s} s (abandoned)")
    if "error" in outcome:
        exc = outcome["error"]
        raise HookFailed(f"{type(exc).__name__}: {exc}")


def _run_shell(spec: HookSpec, command: str, event: dict) -> None:
    payload = json.dumps(event)
    env = {**os.environ, "INSTRUMENT_EVENT": payload, "INSTRUMENT_EVENT_NAME": event["event"]}
    # Own session, so a timeout can stop the whole command (shell and children) by its group id.
    process = subprocess.Popen(command, shell=True, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, env=env, start_new_session=True)
    try:
        _, stderr = process.communicate(payload.encode(), timeout=spec.timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.communicate()
        raise HookFailed(f"shell command did not finish within {spec.timeout_s} s (stopped)") from None
    if process.returncode != 0:
        tail = stderr.decode(errors="replace").strip()[-300:]
        raise HookFailed(f"shell command exited with status {process.returncode}" + (f": {tail}" if tail else ""))


def _run_http(spec: HookSpec, url: str, event: dict) -> None:
    request = urllib.request.Request(url, data=json.dumps(event).encode(), method="POST",
                                     headers={"Content-Type": "application/json"})
    # Never go through a proxy: the target is loopback by validation.
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
    try:
        with opener.open(request, timeout=spec.timeout_s) as response:
            response.read()
    except urllib.error.HTTPError as exc:
        raise HookFailed(f"HTTP {exc.code} from {url}") from None
    except (urllib.error.URLError, OSError) as exc:
        raise HookFailed(f"POST {url} failed: {getattr(exc, 'reason', exc)}") from None


class HookRunner:
    """Runs the hooks of a station and a procedure at each event.

    Parameters
    ----------
    hooks : iterable of HookSpec
    on_failure : callable(message, event), optional
        Told about each failing hook (the engine logs it in the run's event table).
    """

    def __init__(self, hooks: Iterable[HookSpec] = (), on_failure: Callable[[str, dict], None] | None = None) -> None:
        self.hooks = list(hooks)
        self.on_failure = on_failure

    def emit(self, event: dict) -> list[str]:
        """Run every hook subscribed to ``event["event"]``; returns the failure messages."""
        failures = []
        for spec in self.hooks:
            if event["event"] not in spec.events:
                continue
            what = spec.call or spec.entry_point or spec.shell or spec.http
            try:
                if spec.shell:
                    _run_shell(spec, spec.shell, event)
                elif spec.http:
                    _run_http(spec, spec.http, event)
                else:
                    _run_callable(spec, event)
            except Exception as exc:  # a hook never stops the run
                message = f"hook {what!r} on {event['event']}: {exc}"
                failures.append(message)
                if self.on_failure:
                    try:
                        self.on_failure(message, event)
                    except Exception:
                        pass
        return failures
