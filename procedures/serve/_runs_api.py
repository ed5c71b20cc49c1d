"""The web view's API of runs: the list (searched and filtered), the run a live view follows, one run's
summary and figures, its committed samples, its newest streamed move and its events (all SI)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Query

from instrument import __version__
from procedures.report import iso_points
from procedures.serve._http import Reader, Settings, jsonable, snapshot_or_404

router = APIRouter()


@router.get("/api/health")
def health(settings: Settings) -> dict[str, Any]:
    """Liveness and the software version."""
    return {"ok": True, "version": __version__, "runs_dir": str(settings.runs_dir)}


@router.get("/api/runs")
def runs(reader: Reader, q: str = Query("", description="text searched in id, procedure, name, station and reason"),
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
                                                  ("id", "procedure", "name", "title", "station", "reason")).lower())]
    return {"runs": rows[:limit], "matched": len(rows), "current": reader.current_run_id()}


@router.get("/api/runs/current")
def current(reader: Reader) -> dict[str, Any]:
    """The run a live view follows: the newest active run, else the newest run (null: no runs)."""
    return {"run_id": reader.current_run_id()}


@router.get("/api/runs/{run_id}")
def run_detail(reader: Reader, run_id: str) -> dict[str, Any]:
    """Summary with progress, parameters, per-point figures (ISO runs) and the full results (SI)."""
    snap = snapshot_or_404(reader, run_id)
    run = reader.run(run_id)
    return jsonable({"run": snap["run"], "parameters": run.get("parameters"), "results": run.get("results"),
                     "iso_points": iso_points(run.get("results") or {})})


@router.get("/api/runs/{run_id}/points")
def points(reader: Reader, run_id: str,
           after: int = Query(-1, description="only steps with a greater index")) -> dict[str, Any]:
    """Every committed sample: step, key, label, phase, cycle, ok, error, pose [x,y,z,a,b,c] (m, rad)."""
    return jsonable({"points": [p for p in snapshot_or_404(reader, run_id)["points"] if p["step"] > after]})


@router.get("/api/runs/{run_id}/posestream")
def posestream(reader: Reader, run_id: str) -> dict[str, Any]:
    """The newest move measured in motion: ``t`` (s from the done signal), ``distance`` (m, to the attained
    pose), ``step``, ``key``, ``rate_hz``, ``dropped``, ``poses``; ``{"step": null}`` when the run has none."""
    snap = snapshot_or_404(reader, run_id)
    return jsonable(reader.latest_stream(snap["run"]["id"]) or {"step": None})


@router.get("/api/runs/{run_id}/events")
def events(reader: Reader, run_id: str) -> dict[str, Any]:
    """The run's events (state changes, set-ups, dry run, retries, failed hooks), oldest first."""
    return {"events": snapshot_or_404(reader, run_id)["events"]}
