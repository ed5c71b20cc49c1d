"""The web view's API of camera frames: a run's newest frame triple (with its crosses and fitted lines) and
each frame as a reduced PNG."""

from __future__ import annotations

from pathlib import Path
from typing import Any
from urllib.parse import quote

from fastapi import APIRouter, HTTPException, Query
from fastapi.responses import Response

from instrument import SCREENS
from procedures.serve._frames import frame_png, latest_frames
from procedures.serve._http import Reader, Settings, snapshot_or_404

router = APIRouter()


@router.get("/api/runs/{run_id}/frames")
def frames(reader: Reader, settings: Settings, run_id: str) -> dict[str, Any]:
    """The newest frame triple: per screen the image address, the cross and its two fitted lines (px)."""
    snap = snapshot_or_404(reader, run_id)
    return {"frames": frames_payload(settings.runs_dir, snap)}


@router.get("/api/runs/{run_id}/frames/{screen}.png", response_class=Response)
def frame_image(reader: Reader, settings: Settings, run_id: str, screen: str,
                file: str = Query(..., description="as given by /frames")) -> Response:
    """One frame as PNG (reduced). ``file`` is the one ``/api/runs/RUN/frames`` named."""
    if screen not in SCREENS:
        raise HTTPException(404, f"no screen {screen!r}; screens are x, y, z")
    run = snapshot_or_404(reader, run_id)["run"]
    try:
        body = frame_png(settings.runs_dir / run["id"], file)
    except (OSError, ValueError):
        raise HTTPException(404, f"no frame {file!r} (a newer pose may have replaced it)") from None
    return Response(body, media_type="image/png", headers={"Cache-Control": "max-age=3600"})


def frames_payload(runs_dir: Path, snap: dict[str, Any]) -> dict[str, Any] | None:
    """The newest frame triple of a snapshot's run, each screen with the address of its image."""
    run_id = snap["run"]["id"]
    try:
        found = latest_frames(runs_dir / run_id, snap["samples"])
    except (OSError, ValueError):
        return None
    if found is None:
        return None
    for screen, entry in found["screens"].items():
        entry["url"] = f"/api/runs/{run_id}/frames/{screen}.png?file={quote(entry['file'])}"
    return found
