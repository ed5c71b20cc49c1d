"""The web view: a FastAPI app with a few plain HTML/JS/SVG pages and the JSON API they use.

Pages: ``/`` runs list (search and filters), ``/live`` the current run (``/runs/RUN`` one run),
``/runs/RUN/report`` the run's HTML report, ``/robots`` each robot's RP history. API under ``/api``
(docs/web_view.md; the schema at ``/openapi.json``). Live updates are server-sent events: one task
polls the store's change counter (``StoreReader.version``) and every open stream reads the store again
only when it changed. Everything the API returns is SI (m, rad, s); the pages convert.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote

from fastapi import FastAPI, HTTPException, Query, Request
from fastapi.responses import FileResponse, HTMLResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from starlette.concurrency import run_in_threadpool

from instrument import __version__
from procedures.report import history_procedures, iso_points
from procedures.serve._frames import SCREENS, frame_png, latest_frames
from procedures.serve._reader import StoreReader
from procedures.serve._security import AccessGuard

STATIC = Path(__file__).parent / "static"
KEEP_ALIVE_S = 15.0


@dataclass(frozen=True)
class WebSettings:
    """How the web view is served.

    runs_dir : the runs folder (``runs.sqlite`` and one folder per run)
    token : required on every request when set (``--allow-remote`` always sets one)
    loopback_only : refuse requests whose ``Host`` is not a loopback name
    poll_interval_s : how often the store's change counter is read
    """

    runs_dir: Path
    token: str | None = None
    loopback_only: bool = True
    poll_interval_s: float = 0.25


class StoreWatcher:
    """One task that reads the store's change counter and wakes every waiting stream when it moves."""

    def __init__(self, reader: StoreReader, interval_s: float) -> None:
        self.reader, self.interval_s = reader, interval_s
        self.version = -1
        self._changed = asyncio.Event()

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
        if self.version == seen:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._changed.wait(), timeout)
        return self.version


def _sse(event: str, data: Any) -> str:
    return f"event: {event}\ndata: {json.dumps(data, default=str, allow_nan=False)}\n\n"


def _jsonable(value: Any) -> Any:
    """NaN and infinities (a failed statistic) become null: JSON has no such numbers."""
    if isinstance(value, float):
        return value if value == value and abs(value) != float("inf") else None
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


def create_app(settings: WebSettings, *, reader: StoreReader | None = None) -> FastAPI:
    """The web view on the store in ``settings.runs_dir`` (an ASGI app; ``instrument serve`` runs it).

    Parameters
    ----------
    settings : where the runs are and who may read them
    reader : a ``StoreReader`` to share (the OPC UA server uses the same one); made here when None
    """
    reader = reader if reader is not None else StoreReader(settings.runs_dir)
    watcher = StoreWatcher(reader, settings.poll_interval_s)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        task = asyncio.create_task(watcher.run())
        try:
            yield
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    app = FastAPI(title="OPR repeatability — instrument web view", version=__version__, lifespan=lifespan,
                  docs_url=None, redoc_url=None)  # Swagger's pages load scripts from a CDN; /openapi.json stays
    app.state.reader, app.state.watcher = reader, watcher
    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    def page(name: str) -> Callable[[], FileResponse]:
        def serve_page() -> FileResponse:
            return FileResponse(STATIC / name, media_type="text/html")
        return serve_page

    app.add_api_route("/", page("runs.html"), include_in_schema=False)
    app.add_api_route("/live", page("run.html"), include_in_schema=False)
    app.add_api_route("/runs/{run_id}", page("run.html"), include_in_schema=False)
    app.add_api_route("/robots", page("robots.html"), include_in_schema=False)

    def find(run_id: str) -> dict[str, Any]:
        try:
            return reader.snapshot(run_id)
        except KeyError as exc:
            raise HTTPException(404, exc.args[0]) from None

    @app.get("/runs/{run_id}/report", response_class=HTMLResponse, include_in_schema=False)
    def report(run_id: str) -> HTMLResponse:
        from procedures.report import render_report  # the measurement stack loads only when a report is asked

        try:
            run = reader.run(run_id)
        except KeyError as exc:
            raise HTTPException(404, exc.args[0]) from None
        return HTMLResponse(render_report(run, reader.samples(run["id"]), reader.events(run["id"])))

    @app.get("/api/health")
    def health() -> dict[str, Any]:
        """Liveness and the software version."""
        return {"ok": True, "version": __version__, "runs_dir": str(settings.runs_dir)}

    @app.get("/api/runs")
    def runs(q: str = Query("", description="text searched in id, procedure, name, station and reason"),
             state: str = Query("", description="only runs in this state (RUNNING, FINISHED ...)"),
             procedure: str = Query("", description="only runs of this procedure kind"),
             robot: str = Query("", description="only runs of this robot key (see /api/robots)"),
             limit: int = Query(200, ge=1, le=10000)) -> dict[str, Any]:
        """Runs, newest first, filtered; ``current`` is the run ``/live`` follows."""
        needle = q.strip().lower()
        rows = [r for r in reader.runs()
                if (not state or r["state"] == state.upper()) and (not procedure or r["procedure"] == procedure)
                and (not robot or r["robot"]["key"] == robot)
                and (not needle or needle in " ".join(str(r.get(k) or "") for k in
                                                      ("id", "procedure", "name", "station", "reason")).lower())]
        return {"runs": rows[:limit], "matched": len(rows), "current": reader.current_run_id()}

    @app.get("/api/runs/current")
    def current() -> dict[str, Any]:
        """The run a live view follows: the newest active run, else the newest run (null: no runs)."""
        return {"run_id": reader.current_run_id()}

    @app.get("/api/runs/{run_id}")
    def run_detail(run_id: str) -> dict[str, Any]:
        """Summary with progress, parameters, per-point figures (ISO runs) and the full results (SI)."""
        snap = find(run_id)
        run = reader.run(run_id)
        return _jsonable({"run": snap["run"], "parameters": run.get("parameters"), "results": run.get("results"),
                          "iso_points": iso_points(run.get("results") or {})})

    @app.get("/api/runs/{run_id}/points")
    def points(run_id: str, after: int = Query(-1, description="only steps with a greater index")) -> dict[str, Any]:
        """Every committed sample: step, key, label, phase, cycle, ok, error, pose [x,y,z,a,b,c] (m, rad)."""
        return _jsonable({"points": [p for p in find(run_id)["points"] if p["step"] > after]})

    @app.get("/api/runs/{run_id}/posestream")
    def posestream(run_id: str) -> dict[str, Any]:
        """The newest move measured in motion: ``t`` (s from the done signal), ``distance`` (m, to the attained
        pose), ``step``, ``key``, ``rate_hz``, ``dropped``, ``poses``; ``{"step": null}`` when the run has none."""
        snap = find(run_id)
        return _jsonable(reader.latest_stream(snap["run"]["id"]) or {"step": None})

    @app.get("/api/runs/{run_id}/events")
    def events(run_id: str) -> dict[str, Any]:
        """The run's events (state changes, set-ups, dry run, retries, failed hooks), oldest first."""
        return {"events": find(run_id)["events"]}

    @app.get("/api/runs/{run_id}/frames")
    def frames(run_id: str) -> dict[str, Any]:
        """The newest frame triple: per screen the image address, the cross and its two fitted lines (px)."""
        snap = find(run_id)
        return {"frames": _frames_payload(settings.runs_dir, snap)}

    @app.get("/api/runs/{run_id}/frames/{screen}.png", response_class=Response)
    def frame_image(run_id: str, screen: str, file: str = Query(..., description="as given by /frames")) -> Response:
        """One frame as PNG (reduced). ``file`` is the one ``/api/runs/RUN/frames`` named."""
        if screen not in SCREENS:
            raise HTTPException(404, f"no screen {screen!r}; screens are x, y, z")
        run = find(run_id)["run"]
        try:
            body = frame_png(settings.runs_dir / run["id"], file)
        except (OSError, ValueError):
            raise HTTPException(404, f"no frame {file!r} (a newer pose may have replaced it)") from None
        return Response(body, media_type="image/png", headers={"Cache-Control": "max-age=3600"})

    @app.get("/api/robots")
    def robots() -> dict[str, Any]:
        """Robots seen in the store: by identity (serial) when a run records it, else by station name;
        ``iso_runs`` counts the finished runs of the kinds a robot's history follows."""
        groups: dict[str, dict[str, Any]] = {}
        followed = history_procedures()
        for r in reader.runs():
            group = groups.setdefault(r["robot"]["key"], {**r["robot"], "runs": 0, "iso_runs": 0, "last": None})
            group["runs"] += 1
            group["iso_runs"] += int(r["procedure"] in followed and r["state"] == "FINISHED")
            group["last"] = max(group["last"] or 0, r["created"] or 0)
        return {"robots": sorted(groups.values(), key=lambda g: -(g["last"] or 0))}

    @app.get("/api/robots/history")
    def robot_history(key: str = Query(..., description="a robot key from /api/robots")) -> dict[str, Any]:
        """RP and AP per point of each finished ISO 9283 run of one robot, oldest first (SI, with intervals)."""
        return _jsonable({"key": key, "history": reader.iso_history(key)})

    @app.get("/api/changes")
    async def changes(request: Request) -> StreamingResponse:
        """Server-sent events: ``version`` each time the store changes (the runs list refreshes on it)."""
        async def stream() -> AsyncIterator[str]:
            seen = -2
            while True:
                version = await watcher.wait(seen, KEEP_ALIVE_S)
                if version == seen:
                    yield ": keep-alive\n\n"
                    continue
                seen = version
                yield _sse("version", {"version": version})
        return _event_stream(stream())

    @app.get("/api/runs/{run_id}/stream")
    async def run_stream(run_id: str, request: Request) -> StreamingResponse:
        """Server-sent events of one run (``current``: the run ``/live`` follows, switching when a new run
        starts): ``switch`` (a new run), ``run`` (summary and progress), ``points`` (new samples),
        ``events`` (new events), ``frames`` (a newer frame triple), ``posestream`` (the newest move measured in
        motion: distance to its attained pose over time), ``results`` (once the run has them)."""
        return _event_stream(_follow(run_id))

    async def _follow(requested: str) -> AsyncIterator[str]:
        follow = requested == "current"
        seen, run_id = -2, None
        sent_steps: set[int] = set()
        sent_events, frames_step, results_sent = 0, None, False
        stream_step: int | None = None
        while True:
            version = await watcher.wait(seen, KEEP_ALIVE_S)
            if version == seen:
                yield ": keep-alive\n\n"
                continue
            seen = version
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
            yield _sse("run", _jsonable(snap["run"]))
            fresh = [p for p in snap["points"] if p["step"] not in sent_steps]
            if fresh:
                sent_steps.update(p["step"] for p in fresh)
                yield _sse("points", _jsonable(fresh))
            if len(snap["events"]) > sent_events:
                yield _sse("events", snap["events"][sent_events:])
                sent_events = len(snap["events"])
            frames = await run_in_threadpool(_frames_payload, settings.runs_dir, snap)
            if frames is not None and frames["step"] != frames_step:
                frames_step = frames["step"]
                yield _sse("frames", _jsonable(frames))
            motion = await run_in_threadpool(reader.latest_stream, snap["run"]["id"])
            if motion is not None and motion["step"] != stream_step:
                stream_step = motion["step"]
                yield _sse("posestream", _jsonable(motion))
            if snap["results"] and not results_sent:
                results_sent = True
                yield _sse("results", _jsonable({"iso_points": iso_points(snap["results"]),
                                                 "kind": snap["results"].get("kind")}))

    app.add_middleware(AccessGuard, token=settings.token, loopback_only=settings.loopback_only)
    return app


def _frames_payload(runs_dir: Path, snap: dict[str, Any]) -> dict[str, Any] | None:
    run_id = snap["run"]["id"]
    try:
        frames = latest_frames(runs_dir / run_id, snap["samples"])
    except (OSError, ValueError):
        return None
    if frames is None:
        return None
    for screen, entry in frames["screens"].items():
        entry["url"] = f"/api/runs/{run_id}/frames/{screen}.png?file={quote(entry['file'])}"
    return frames


def _event_stream(events: AsyncIterator[str]) -> StreamingResponse:
    return StreamingResponse(events, media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})
