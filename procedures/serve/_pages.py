"""The web view's pages: plain HTML files from ``static/`` (their scripts read the API), and a run's report."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from fastapi import APIRouter, HTTPException
from fastapi.responses import FileResponse, HTMLResponse

from procedures.serve._http import Reader

STATIC = Path(__file__).parent / "static"


def _page(name: str) -> Callable[[], FileResponse]:
    def serve_page() -> FileResponse:
        return FileResponse(STATIC / name, media_type="text/html")
    return serve_page


router = APIRouter()
router.add_api_route("/", _page("runs.html"), include_in_schema=False)
router.add_api_route("/live", _page("run.html"), include_in_schema=False)
router.add_api_route("/runs/{run_id}", _page("run.html"), include_in_schema=False)
router.add_api_route("/robots", _page("robots.html"), include_in_schema=False)


@router.get("/runs/{run_id}/report", response_class=HTMLResponse, include_in_schema=False)
def report(reader: Reader, run_id: str) -> HTMLResponse:
    from procedures.report import render_report  # the measurement stack loads only when a report is asked

    try:
        run = reader.run(run_id)
    except KeyError as exc:
        raise HTTPException(404, exc.args[0]) from None
    return HTMLResponse(render_report(run, reader.samples(run["id"]), reader.events(run["id"])))
