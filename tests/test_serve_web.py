"""The web view's API and security on runs made by the engine on the fake cell (known truth), the
live frames file, and the fitted stripe lines drawn over a synthetic cross of known geometry."""

from __future__ import annotations

import json
import threading
import warnings

import numpy as np
import pytest

from instrument.vision import locate_cross
from procedures.engine import open_engine
from procedures.serve import StoreReader, WebSettings, create_app, latest_frames, stripe_lines, write_live_frames
from procedures.store import RunStore
from tests.fakes import FakeCell, FakeScience, write_station
from tests.synthetic_cross import render_cross

with warnings.catch_warnings():  # starlette's TestClient announces a future client package on import
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient` is deprecated")
    from fastapi.testclient import TestClient

pytestmark = pytest.mark.timeout(120)


def _procedure(tmp_path, kind, **params):
    body = ", ".join(f"{k}: {v}" for k, v in {"settle_time_s": 0, "frames_per_pose": 1, **params}.items())
    path = tmp_path / f"{kind}.yaml"
    path.write_text(f"procedure: {kind}\nparameters: {{{body}}}\n")
    return path


def _run(tmp_path, station_name="fake cell", cycles=3, seed=2):
    truth = tmp_path / f"truth-{seed}.jsonl"
    station = write_station(tmp_path / f"station-{seed}.yaml", truth_log=str(truth), name=station_name)
    cell = FakeCell(seed=seed, truth_log=truth)
    with open_engine(tmp_path / "runs", procedure=_procedure(tmp_path, "iso9283_repeatability", cycles=cycles),
                     station=station, science=FakeScience(cell), devices=cell.devices(),
                     operator=cell.operator) as engine:
        assert engine.execute() == "FINISHED"
        return engine.run_id


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("web")
    first = _run(tmp_path, "fake cell", cycles=3, seed=2)
    second = _run(tmp_path, "second cell", cycles=4, seed=3)
    return tmp_path / "runs", first, second


@pytest.fixture
def client(store):
    runs_dir = store[0]
    with TestClient(create_app(WebSettings(runs_dir=runs_dir)), base_url="http://127.0.0.1") as test_client:
        yield test_client


def test_runs_list_filters_and_current(client, store):
    _, first, second = store
    every = client.get("/api/runs").json()
    assert [r["id"] for r in every["runs"]] == [second, first]  # newest first
    assert every["current"] == second
    assert [r["id"] for r in client.get("/api/runs", params={"q": "second"}).json()["runs"]] == [second]
    assert client.get("/api/runs", params={"state": "failed"}).json()["runs"] == []
    # The fake cells' robot reports one serial (tests/fakes.py): both runs were measured on it.
    only = client.get("/api/runs", params={"robot": "serial:20235500123"}).json()["runs"]
    assert [r["id"] for r in only] == [second, first]
    assert only[1]["done"] == only[1]["total"] == 5 + 3 * 5


def test_points_and_figures_are_the_stored_ones(client, store):
    runs_dir, first, _ = store
    with RunStore(runs_dir) as runs:
        samples = runs.samples(first)
        results = runs.get_run(first)["results"]
    points = client.get(f"/api/runs/{first}/points").json()["points"]
    assert [p["key"] for p in points] == [s.step_key for s in samples]
    for point, sample in zip(points, samples):
        assert point["pose"] == pytest.approx(sample.pose)
    assert len(client.get(f"/api/runs/{first}/points", params={"after": 9}).json()["points"]) == len(samples) - 10
    detail = client.get(f"/api/runs/{first}").json()
    for label, figures in detail["iso_points"].items():
        stats = results["points"][label]["stats"]
        assert figures["rp_l"] == pytest.approx(stats["rp_l"])
        assert figures["rp_l_ci"] == pytest.approx(stats["rp_l_ci"])
        # the fake instrument's RP_l is its truth's within its noise (tests/test_engine.py)
        assert figures["rp_l"] == pytest.approx(results["points"][label]["true_stats"]["rp_l"], abs=1e-6)
    assert detail["run"]["phase"] == "iso" and detail["run"]["cycle"] == 2


def test_robot_history_groups_by_the_serial_the_controller_reported(client, store):
    _, first, second = store
    robots = {r["key"]: r for r in client.get("/api/robots").json()["robots"]}
    assert set(robots) == {"serial:20235500123"}  # two stations, one robot (its serial read at run start)
    assert all(r["source"] == "identity" and r["iso_runs"] == 2 for r in robots.values())
    history = client.get("/api/robots/history", params={"key": "serial:20235500123"}).json()["history"]
    assert [h["run"]["id"] for h in history] == [first, second]
    assert set(history[1]["points"]) == {"P1", "P2", "P3", "P4", "P5"} and history[1]["points"]["P1"]["n"] == 4


def test_report_pages_and_unknown_runs(client, store):
    _, first, _ = store
    report = client.get(f"/runs/{first}/report")
    assert report.status_code == 200 and first in report.text and "RP" in report.text
    for page in ("/", "/live", f"/runs/{first}", "/robots", "/static/live.js"):
        assert client.get(page).status_code == 200, page
    missing = client.get("/api/runs/ffffffff")
    assert missing.status_code == 404 and "no run" in missing.json()["detail"]


def test_stream_sends_the_run_its_points_and_events(client, store):
    _, first, _ = store
    events: dict[str, list] = {}
    with client.stream("GET", f"/api/runs/{first}/stream") as response:
        assert response.headers["content-type"].startswith("text/event-stream")
        name = None
        for line in response.iter_lines():
            if line.startswith("event: "):
                name = line[7:]
            elif line.startswith("data: ") and name:
                events.setdefault(name, []).append(json.loads(line[6:]))
            if "results" in events:
                break
    assert events["switch"][0]["run_id"] == first
    assert events["run"][0]["state"] == "FINISHED"
    assert len(events["points"][0]) == 5 + 3 * 5
    assert any(e["kind"] == "dry_run" for e in events["events"][0])
    assert set(events["results"][0]["iso_points"]) == {"P1", "P2", "P3", "P4", "P5"}


def test_loopback_view_refuses_foreign_host_names(store):
    app = create_app(WebSettings(runs_dir=store[0]))
    with TestClient(app, base_url="http://127.0.0.1") as local:
        assert local.get("/api/health").status_code == 200
    with TestClient(app, base_url="http://rebound.example") as foreign:
        refused = foreign.get("/api/health")
        assert refused.status_code == 400 and "loopback" in refused.json()["error"]


def test_token_is_required_on_every_request_and_set_as_a_cookie(store):
    app = create_app(WebSettings(runs_dir=store[0], token="s3cret", loopback_only=False))
    with TestClient(app, base_url="http://10.1.2.3") as client:
        assert client.get("/api/runs").status_code == 401
        assert client.get("/api/runs", headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert client.get("/api/runs", headers={"Authorization": "Bearer s3cret"}).status_code == 200
        opened = client.get("/live?token=s3cret", follow_redirects=False)
        assert opened.status_code == 303 and opened.headers["location"] == "/live"
        assert "HttpOnly" in opened.headers["set-cookie"]
        assert client.get("/api/runs").status_code == 200  # the cookie now carries it


def test_stripe_lines_lie_on_the_stripes_of_a_known_cross():
    image, truth = render_cross(shape=(240, 320), center=(150.3, 118.7), angle=0.2, perpendicularity=0.05, seed=4)
    found = locate_cross(image)
    cross = {"center_px": [float(v) for v in found.center], "angle_rad": float(found.angle),
             "perpendicularity_rad": float(found.perpendicularity)}
    lines = stripe_lines(cross, 320, 240)
    assert lines["center"] == pytest.approx(truth.center, abs=0.05)
    for part in ("horizontal", "vertical"):
        (x0, y0), (x1, y1) = lines[part]
        direction = np.array([x1 - x0, y1 - y0]) / np.hypot(x1 - x0, y1 - y0)
        normal = np.array([-direction[1], direction[0]])
        for distance in (-60, -30, 30, 60):  # along the line, away from the crossing
            on = truth.center + distance * direction
            off = on + 8 * normal  # four stripe sigmas to the side
            assert image[int(round(on[1])), int(round(on[0]))] > 150, (part, distance)
            assert image[int(round(off[1])), int(round(off[0]))] < 40, (part, distance)


def test_live_frames_file_is_newest_and_atomic(tmp_path, store):
    runs_dir, first, _ = store
    with RunStore(runs_dir) as runs:
        samples = runs.samples(first)
    image, _ = render_cross(shape=(240, 320), seed=1)
    run_dir = tmp_path / "run"
    assert latest_frames(run_dir, samples) is None  # the fake cell saves no frames
    cross = {"center_px": [160.0, 120.0], "angle_rad": 0.0, "perpendicularity_rad": 0.0}
    index = write_live_frames(run_dir, 7, "iso/c000/P2", {"x": image, "y": image, "z": image}, {"x": cross, "y": None})
    assert index is not None and json.loads(index.read_text())["step"] == 7
    frames = latest_frames(run_dir, samples)
    assert frames is not None and frames["source"] == "live" and frames["size"] == [320, 240]
    assert frames["screens"]["x"]["lines"]["center"] == [160.0, 120.0]
    assert frames["screens"]["y"]["lines"] is None
    write_live_frames(run_dir, 8, "iso/c000/P3", {"x": image, "y": image, "z": image})
    assert sorted(p.name for p in (run_dir / "live").glob("*.png")) == ["00008_x.png", "00008_y.png", "00008_z.png"]


def test_the_reader_sees_commits_of_another_connection(tmp_path):
    reader = StoreReader(tmp_path / "runs")
    try:
        before = reader.version()
        seen = []

        def write():
            with RunStore(tmp_path / "runs") as store:  # another connection, as the engine's
                store.create_run(procedure="iso9283_repeatability", parameters={}, station={}, software_version="t",
                                 station_name="bench", total_steps=3)
            seen.append(True)

        thread = threading.Thread(target=write)
        thread.start()
        thread.join(30)
        assert seen and reader.version() != before
        assert [r["station"] for r in reader.runs()] == ["bench"]
    finally:
        reader.close()
