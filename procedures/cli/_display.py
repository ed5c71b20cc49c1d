"""What a run shows while it runs: a progress display fitted to the terminal, or heartbeat lines.

On a terminal (stderr is a TTY) a ``rich`` live display: one line with the phase (k/N), the plan's
position (cycle, axis, group), a bar that takes the width that is left, done/total and the ETA; a
second line with the last pose and its solver residual. Both are cut to the terminal's width, so an
update never wraps. Anywhere else (a file, a pipe, CI) a **heartbeat**: one plain line every
``heartbeat_s`` (10 s) with the same facts, also while a set-up or a wait holds the run, plus a line
for every state change, set-up and dry run. ``--jsonl`` mode prints each event as one JSON line on
stdout; ``quiet`` prints nothing (the command prints its one line at the end).

The ETA comes from the engine (``eta_s`` of the progress event: this run's remaining steps at the
recent pace plus its remaining set-ups at their mean duration); a caller running several runs in a
row (``make demo``) adds what follows through ``later_s``.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, TextIO

from rich.console import Console, Group
from rich.live import Live
from rich.progress import BarColumn, Progress, ProgressColumn, Task, TaskID, TextColumn
from rich.table import Column
from rich.text import Text

HEARTBEAT_S = 10.0


def analysis_text(event: dict[str, Any]) -> str:
    """``analysing (uncertainty, 3 of 9)``; ``analysing the results`` before a stage has reported."""
    if event.get("total"):
        return f"analysing ({event.get('stage')}, {event.get('done')} of {event.get('total')})"
    return "analysing the results"


def clock(seconds: float | None) -> str:
    """``h:mm:ss`` (``--:--`` when unknown)."""
    if seconds is None:
        return "--:--"
    seconds = int(max(seconds, 0))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def where_text(event: dict[str, Any]) -> str:
    """The plan position of a progress event: ``cycle 3/30 P4`` or ``axis y group 2/3 y=5 mm``."""
    parts = []
    if event.get("cycle") is not None:
        parts.append(f"cycle {int(event['cycle']) + 1}/{event.get('cycles', '?')}")
    if event.get("axis") is not None:
        parts.append(f"axis {event['axis']}")
    if event.get("group") is not None:
        parts.append(f"group {int(event['group']) + 1}/{event.get('groups', '?')}")
    if event.get("label"):
        parts.append(str(event["label"]))
    return " ".join(parts)


def pose_text(event: dict[str, Any]) -> str:
    """The last measured pose of a ``point_measured`` event, in mm and µm."""
    pose = event.get("pose")
    if event.get("ok") and pose:
        return (f"{event.get('label')}: x {pose[0] * 1e3:.4f} y {pose[1] * 1e3:.4f} z {pose[2] * 1e3:.4f} mm  "
                f"residual {(event.get('residual_rms') or 0) * 1e6:.2f} µm")
    return f"{event.get('label')}: FAILED {(str(event.get('error')).splitlines() or [''])[0]}"


class _Eta(ProgressColumn):
    """The engine's ETA (plus what follows this run), not rich's own speed estimate."""

    def render(self, task: Task) -> Text:
        return Text(f"ETA {clock(task.fields.get('eta'))}", no_wrap=True)


class _View:
    def __init__(self, progress: Progress) -> None:
        self.progress = progress
        self.last = Text("", no_wrap=True, overflow="ellipsis")

    def __rich__(self) -> Group:
        return Group(self.progress, self.last)


class Display:
    """A run's listener: ``mode`` ``bar`` (terminal display or heartbeat), ``quiet`` or ``jsonl``.

    Parameters
    ----------
    mode : ``bar`` shows progress on ``stream``; ``quiet`` nothing; ``jsonl`` every event on stdout
    stream : where progress goes (default stderr); a terminal gets the live display, else heartbeats
    heartbeat_s : seconds between heartbeat lines when ``stream`` is not a terminal
    phase : ``(k, n)`` when this run is one of several in a row (``make demo``), shown as ``k/n``
    later_s : callable giving the seconds the runs after this one will take (added to the ETA)
    """

    def __init__(self, mode: str = "bar", stream: TextIO | None = None, *, heartbeat_s: float = HEARTBEAT_S,
                 phase: tuple[int, int] | None = None, later_s: Callable[[], float] | None = None) -> None:
        self.mode = mode
        self.stream = stream or sys.stderr
        self.heartbeat_s = heartbeat_s
        self.phase = phase
        self.later_s = later_s
        self.last_progress: dict[str, Any] = {}
        self.analysis: dict[str, Any] = {}  # the last "analysis" event, once the poses are done
        self.last_pose = ""
        self.started = time.monotonic()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._heartbeat: threading.Thread | None = None
        self._live: Live | None = None
        self._progress: Progress | None = None
        self._view: _View | None = None
        self._task: TaskID | None = None
        self.terminal = mode == "bar" and bool(getattr(self.stream, "isatty", lambda: False)())
        self._console = Console(file=self.stream, force_terminal=self.terminal or None, highlight=False,
                                soft_wrap=False)

    # ------------------------------------------------------------------------------ lifecycle
    def __enter__(self) -> Display:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> None:
        """Start the live display (terminal) or the heartbeat thread (anything else)."""
        if self.mode != "bar" or self._live is not None or self._heartbeat is not None:
            return
        self.started = time.monotonic()
        if self.terminal:
            self._progress = Progress(
                TextColumn("{task.description}", table_column=Column(no_wrap=True, overflow="ellipsis", ratio=2)),
                BarColumn(bar_width=None, table_column=Column(ratio=1, min_width=10)),
                TextColumn("{task.completed}/{task.total}", table_column=Column(no_wrap=True)),
                _Eta(table_column=Column(no_wrap=True)),
                console=self._console, expand=True, auto_refresh=False)
            self._task = self._progress.add_task(self._title({}), total=None, eta=None)
            self._view = _View(self._progress)
            self._live = Live(self._view, console=self._console, refresh_per_second=4, transient=False)
            self._live.start()
        else:
            self._stop.clear()
            self._heartbeat = threading.Thread(target=self._beat, name="heartbeat", daemon=True)
            self._heartbeat.start()

    def stop(self) -> None:
        if self._live is not None:
            self._live.stop()
            self._live = None
        if self._heartbeat is not None:
            self._stop.set()
            self._heartbeat.join(timeout=5)
            self._heartbeat = None

    # --------------------------------------------------------------------------------- events
    def __call__(self, event: dict[str, Any]) -> None:
        if self.mode == "jsonl":
            print(json.dumps(event, default=str), flush=True)
            return
        if self.mode == "quiet":
            return
        if self._live is None and self._heartbeat is None:
            self.start()  # a listener used without ``with``
        kind = event.get("event")
        with self._lock:
            if kind == "point_measured":
                self.last_pose = pose_text(event)
                if self._view is not None:
                    self._view.last = Text(self.last_pose, no_wrap=True, overflow="ellipsis")
            elif kind == "stream":  # a move measured in motion: one per streamed second
                distance = event.get("distance_to_target")
                self.last_pose = (f"streaming {event.get('key', '')}: t {event.get('t', 0.0):.2f} s, "
                                  + (f"{distance * 1e6:.1f} µm from target, " if distance is not None else "")
                                  + f"{event.get('rate_hz') or 0:g} Hz, {event.get('dropped', 0)} dropped")
                if self._view is not None:
                    self._view.last = Text(self.last_pose, no_wrap=True, overflow="ellipsis")
            elif kind == "progress":
                self.last_progress = event
                if self._progress is not None and self._task is not None:
                    self._progress.update(self._task, description=self._title(event), completed=event["done"],
                                          total=event["total"], eta=self._eta(event))
            elif kind == "analysis":
                self.analysis = event
                if self._progress is not None and self._task is not None:
                    self._progress.update(self._task, description=analysis_text(event), eta=event.get("eta_s"))
            elif kind == "state":
                self._line(f"{time.strftime('%H:%M:%S')} {event['state']}"
                           + (f": {(str(event['reason']).splitlines() or [''])[0]}" if event.get("reason") else ""))
            elif kind == "dry_run":
                problems = event.get("problems") or []
                self._line(f"dry run: {event['steps']} steps checked, {len(problems)} problems")
            elif kind == "setup":
                self._line(f"set-up: {event['setup']}")
        if self._live is not None:
            self._live.refresh()

    def _title(self, event: dict[str, Any]) -> str:
        """Most telling first (a narrow terminal cuts the end): the demo's phase, the plan position, the
        procedure's phase, the procedure."""
        parts = []
        if self.phase is not None:
            parts.append(f"{self.phase[0]}/{self.phase[1]}")
        where = where_text(event)
        if where:
            parts.append(where)
        if (event.get("phases") or 0) > 1:
            parts.append(f"{event.get('phase')} {event.get('phase_index')}/{event.get('phases')}")
        if event.get("procedure"):
            parts.append(str(event["procedure"]))
        return " · ".join(parts) or "starting"

    def _eta(self, event: dict[str, Any]) -> float | None:
        eta = event.get("eta_s")
        if eta is None:
            return None
        return float(eta) + (self.later_s() if self.later_s is not None else 0.0)

    def status_line(self) -> str:
        """The heartbeat's line: elapsed time, phase, position, done/total, ETA."""
        event = self.last_progress
        elapsed = clock(time.monotonic() - self.started)
        if not event:
            return f"{time.strftime('%H:%M:%S')} [{elapsed}] {self._title({})}: setting up"
        done, total = event["done"], event["total"]
        if self.analysis:  # the poses are done: what runs now is the analysis, with its own ETA
            eta = self.analysis.get("eta_s")
            return (f"{time.strftime('%H:%M:%S')} [{elapsed}] {analysis_text(self.analysis)} · {done}/{total} poses "
                    f"measured · ETA {clock(eta)}")
        eta = self._eta(event)
        waited = time.time() - float(event.get("time") or time.time())
        waiting = f" · waiting {waited:.0f} s since the last pose" if waited >= self.heartbeat_s else ""
        return (f"{time.strftime('%H:%M:%S')} [{elapsed}] {self._title(event)} · {done}/{total} "
                f"({100 * done / max(total, 1):.0f} %) · ETA {clock(eta)}{waiting}")

    def _beat(self) -> None:
        while not self._stop.wait(self.heartbeat_s):
            with self._lock:
                self._line(self.status_line())

    def _line(self, text: str) -> None:
        if self._live is not None:
            self._live.console.print(Text(text, no_wrap=True, overflow="ellipsis"))
        else:
            print(text, file=self.stream, flush=True)
