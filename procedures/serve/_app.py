"""The web view: a FastAPI app with a few plain HTML/JS/SVG pages and the JSON API they use.

Pages: ``/`` runs list (search and filters), ``/live`` the current run (``/runs/RUN`` one run),
``/runs/RUN/report`` the run's HTML report, ``/robots`` each robot's RP history. API under ``/api``
(docs/web_view.md; the schema at ``/openapi.json``). Live updates are server-sent events (``_live``).
Everything the API returns is SI (m, rad, s); the pages convert.

One router per resource, each in its own module: the pages (``_pages``), runs (``_runs_api``), frames
(``_frames_api``), robots (``_robots_api``) and the live streams (``_live``); here they are put together,
in the order their paths must be matched (``/api/runs/current`` before ``/api/runs/{run_id}``).
"""

from __future__ import annotations

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from instrument import __version__
from procedures.serve import _frames_api, _live, _pages, _robots_api, _runs_api
from procedures.serve._http import WebSettings
from procedures.serve._reader import StoreReader
from procedures.serve._security import AccessGuard

ROUTERS = (_pages.router, _runs_api.router, _frames_api.router, _robots_api.router, _live.router)


def create_app(settings: WebSettings, *, reader: StoreReader | None = None) -> FastAPI:
    """The web view on the store in ``settings.runs_dir`` (an ASGI app; ``instrument serve`` runs it).

    Parameters
    ----------
    settings : where the runs are and who may read them
    reader : a ``StoreReader`` to share (the OPC UA server uses the same one); made here when None
    """
    reader = reader if reader is not None else StoreReader(settings.runs_dir)
    watcher, lifespan = _live.watching(reader, settings.poll_interval_s)
    app = FastAPI(title="OPR repeatability — instrument web view", version=__version__, lifespan=lifespan,
                  docs_url=None, redoc_url=None)  # Swagger's pages load scripts from a CDN; /openapi.json stays
    app.state.reader, app.state.watcher, app.state.settings = reader, watcher, settings
    app.mount("/static", StaticFiles(directory=_pages.STATIC), name="static")
    for router in ROUTERS:
        app.include_router(router)
    app.add_middleware(AccessGuard, token=settings.token, loopback_only=settings.loopback_only)
    return app


__all__ = ["WebSettings", "create_app"]
