"""What the web view's routers share: the reader and settings of the app a request came to, a run's
snapshot or a 404, and JSON without NaN."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request

from procedures.serve._reader import StoreReader


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


def reader_of(request: Request) -> StoreReader:
    """The app's ``StoreReader`` (a route's dependency)."""
    reader: StoreReader = request.app.state.reader
    return reader


def settings_of(request: Request) -> WebSettings:
    """The app's ``WebSettings`` (a route's dependency)."""
    settings: WebSettings = request.app.state.settings
    return settings


Reader = Annotated[StoreReader, Depends(reader_of)]
"""A route's parameter: the app's ``StoreReader``."""
Settings = Annotated[WebSettings, Depends(settings_of)]
"""A route's parameter: the app's ``WebSettings``."""


def snapshot_or_404(reader: StoreReader, run_id: str) -> dict[str, Any]:
    """The run's snapshot (``StoreReader.snapshot``), or HTTP 404 naming what is not there."""
    try:
        return reader.snapshot(run_id)
    except KeyError as exc:
        raise HTTPException(404, exc.args[0]) from None


def jsonable(value: Any) -> Any:
    """NaN and infinities (a failed statistic) become null: JSON has no such numbers."""
    if isinstance(value, float):
        return value if value == value and abs(value) != float("inf") else None
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    return value
