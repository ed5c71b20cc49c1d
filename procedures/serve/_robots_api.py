"""The web view's API of robots: the robots the store has runs of, and one robot's history of figures."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Query

from procedures.report import history_procedures
from procedures.serve._http import Reader, jsonable

router = APIRouter()


@router.get("/api/robots")
def robots(reader: Reader) -> dict[str, Any]:
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


@router.get("/api/robots/history")
def robot_history(reader: Reader,
                  key: str = Query(..., description="a robot key from /api/robots")) -> dict[str, Any]:
    """RP and AP per point of each finished ISO 9283 run of one robot, oldest first (SI, with intervals)."""
    return jsonable({"key": key, "history": reader.iso_history(key)})
