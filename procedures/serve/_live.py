"""The web view's live updates: server-sent events that follow the store as the engine writes it.

One task per app (``StoreWatcher``) polls the store's change counter (``StoreReader.version``) and wakes
every open stream when it moves; a stream then reads the store again, so many pages following one run
cost one read per change. ``/api/changes`` says only that the store changed (the runs list refreshes on
it); ``/api/runs/RUN/stream`` follows one run (or ``current``, the run ``/live`` follows).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import StreamingResponse
from starlette.concurrency import run_in_threadpool

from procedures.report import iso_points
from procedures.serve._frames_api import frames_payload
from procedures.serve._http import WebSettings, jsonable, reader_of, settings_of
from procedures.serve._reader import StoreReader

KEEP_ALIVE_S = 15.0


class StoreWatcher:
    """One task that reads the store's change counter and wakes every waiting stream when it moves."""

    def __init__(self, reader: StoreReader, interval_s: float) -> None:
        self.reader, self.interval_s = reader, interval_s
        self.version = -1
        self.closed = False
        self._changed = asyncio.Event()

    def close(self) -> None:
        """End every open stream (the server is shutting down): each returns at once, so the server's
        graceful shutdown finds its connections done instead of cancelling them mid-wait."""
        self.closed = True
        self._changed.set()

    async def run(self) -> None:
        while True:
            try:
                version = await run_in_threadpool(self.reader.version)
            except Exception:  # a store being replaced or locked for a moment: try again next tick
                version = self.version
            if version != self.version:
                self.version = version
                self._changed.set()
                self._changed = asyncio.Event()
            await asyncio.sleep(self.interval_s)

    async def wait(self, seen: int, timeout: float) -> int:
        """The version once it differs from ``seen``, or the same after ``timeout`` seconds."""
        if self.version == seen and not self.closed:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._changed.wait(), timeout)
        return self.version


def watching(reader: StoreReader, interval_s: float) -> tuple[StoreWatcher, Any]:
    """A watcher of ``reader`` and the app lifespan that runs it while the app serves."""
    watcher = StoreWatcher(reader, interval_s)

    @contextlib.asynccontextmanager
    async def lifespan(app: Any) -> AsyncIterator[None]:
        task = asyncio.create_task(watcher.run())
        try:
            yield
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    return watcher, lifespan


def _sse(event: str, data: Any) -> str:
    return f"event: {event}\ndata: {json.dumps(data, default=str, allow_nan=False)}\n\n"


def _event_stream(events: AsyncIterator[str]) -> StreamingResponse:
    return StreamingResponse(events, media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


async def _changes_of(watcher: StoreWatcher) -> AsyncIterator[int | None]:
    """The store's version each time it changes; None after every ``KEEP_ALIVE_S`` without a change.
    Ends once the watcher is closed."""
    seen = -2
    while True:
        version = await watcher.wait(seen, KEEP_ALIVE_S)
        if watcher.closed:
            return
        if version == seen:
            yield None
            continue
        seen = version
        yield version


def _watcher_of(request: Request) -> StoreWatcher:
    watcher: StoreWatcher = request.app.state.watcher
    return watcher


router = APIRouter()


@router.get("/api/changes")
async def changes(request: Request) -> StreamingResponse:
    """Server-sent events: ``version`` each time the store changes (the runs list refreshes on it)."""
    watcher = _watcher_of(request)

    async def stream() -> AsyncIterator[str]:
        async for version in _changes_of(watcher):
            yield ": keep-alive\n\n" if version is None else _sse("version", {"version": version})
    return _event_stream(stream())


@router.get("/api/runs/{run_id}/stream")
async def run_stream(run_id: str, request: Request) -> StreamingResponse:
    """Server-sent events of one run (``current``: the run ``/live`` follows, switching when a new run
    starts): ``switch`` (a new run), ``run`` (summary and progress), ``points`` (new samples),
    ``events`` (new events), ``frames`` (a newer frame triple), ``posestream`` (the newest move measured in
    motion: distance to its attained pose over time), ``results`` (once the run has them)."""
    return _event_stream(_follow(run_id, _watcher_of(request), reader_of(request), settings_of(request)))


async def _follow(requested: str, watcher: StoreWatcher, reader: StoreReader,
                  settings: WebSettings) -> AsyncIterator[str]:
    follow = requested == "current"
    run_id = None
    sent_steps: set[int] = set()
    sent_events, frames_step, results_sent = 0, None, False
    stream_step: int | None = None
    async for version in _changes_of(watcher):
        if version is None:
            yield ": keep-alive\n\n"
            continue
        target = await run_in_threadpool(reader.current_run_id) if follow else requested
        if target is None:
            yield _sse("waiting", {"message": "no runs in the store yet"})
            continue
        try:
            snap = await run_in_threadpool(reader.snapshot, target)
        except KeyError as exc:
            yield _sse("failure", {"message": exc.args[0]})
            return
        if snap["run"]["id"] != run_id:
            run_id = snap["run"]["id"]
            sent_steps, sent_events, frames_step, results_sent = set(), 0, None, False
            stream_step = None
            yield _sse("switch", {"run_id": run_id})
        yield _sse("run", jsonable(snap["run"]))
        fresh = [p for p in snap["points"] if p["step"] not in sent_steps]
        if fresh:
            sent_steps.update(p["step"] for p in fresh)
            yield _sse("points", jsonable(fresh))
        if len(snap["events"]) > sent_events:
            yield _sse("events", snap["events"][sent_events:])
            sent_events = len(snap["events"])
        frames = await run_in_threadpool(frames_payload, settings.runs_dir, snap)
        if frames is not None and frames["step"] != frames_step:
            frames_step = frames["step"]
            yield _sse("frames", jsonable(frames))
        motion = await run_in_threadpool(reader.latest_stream, snap["run"]["id"])
        if motion is not None and motion["step"] != stream_step:
            stream_step = motion["step"]
            yield _sse("posestream", jsonable(motion))
        if snap["results"] and not results_sent:
            results_sent = True
            yield _sse("results", jsonable({"iso_points": iso_points(snap["results"]),
                                            "kind": snap["results"].get("kind")}))
