"""What the commands and the web view give for every run of a store, as bytes: the outputs that must not
change between versions (``test_stored_runs.py``; ``data/make_runs_stored_by_410f450.py`` recorded them).

Only the ``instrument`` command line (``procedures.cli.main``) and the web view's app
(``procedures.serve``) are used: public names that both the version that stored the runs and this one
have. Times are shown in UTC and the report's "report generated" time is blanked, so the bytes depend on
the stored runs alone.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import re
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path

from procedures.cli import main

ROBOT_SERIAL = "20235500123"  # the fake robot's
GENERATED = re.compile(rb"(<th[^>]*>report generated</th><td[^>]*>)[^<]*(</td>)")


@contextlib.contextmanager
def utc() -> Iterator[None]:
    """Local time is UTC inside the block (listings and reports show local times)."""
    before = os.environ.get("TZ")
    os.environ["TZ"] = "UTC"
    time.tzset()
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("TZ", None)
        else:
            os.environ["TZ"] = before
        time.tzset()


def blank_generated(html: bytes) -> bytes:
    """The report with its "report generated" time blanked (the one part that depends on when it is written)."""
    return GENERATED.sub(rb"\1\2", html)


def _captured(argv: list[str]) -> bytes:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(argv)
    assert code == 0, (argv, code)
    return out.getvalue().encode("utf-8")


def outputs(runs: Path, scratch: Path) -> dict[str, bytes]:
    """Name → bytes of ``runs``, ``show``, ``report``, ``export --csv``, ``export --json [--streams]`` of every run,
    ``history [--json]`` of the fake robot, and the web view's ``/api/runs/RUN`` and robot history."""
    from fastapi.testclient import TestClient

    from procedures.serve import WebSettings, create_app

    common = ["--runs-dir", str(runs)]
    with sqlite3.connect(runs / "runs.sqlite") as db:
        ids = [row[0] for row in db.execute("SELECT id FROM runs ORDER BY created")]
    found: dict[str, bytes] = {}
    with utc():
        found["runs"] = _captured(["runs", *common])
        for run_id in ids:
            found[f"show {run_id}"] = _captured(["show", run_id, *common])
            html = scratch / f"{run_id}.html"
            _captured(["report", run_id, "-o", str(html), *common])
            found[f"report {run_id}"] = blank_generated(html.read_bytes())
            found[f"export --csv {run_id}"] = _captured(["export", run_id, "--csv", *common])
            found[f"export --json {run_id}"] = _captured(["export", run_id, "--json", *common])
            found[f"export --json --streams {run_id}"] = _captured(["export", run_id, "--json", "--streams",
                                                                    *common])
        found["history"] = _captured(["history", "--robot", ROBOT_SERIAL, *common])
        found["history --json"] = _captured(["history", "--robot", ROBOT_SERIAL, "--json", *common])
        with TestClient(create_app(WebSettings(runs_dir=runs))) as client:
            for run_id in ids:
                found[f"GET /api/runs/{run_id}"] = client.get(f"/api/runs/{run_id}").content
            found["GET /api/robots/history"] = client.get("/api/robots/history",
                                                          params={"key": f"serial:{ROBOT_SERIAL}"}).content
    return found


def digest(body: bytes) -> str:
    return "sha256:" + hashlib.sha256(body).hexdigest()
