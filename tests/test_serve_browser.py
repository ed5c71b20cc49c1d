"""The live web view in a real browser: Playwright drives Debian's Chromium against ``instrument serve``
while a short simulated ISO 9283 run progresses in another process, and checks that the live page
follows it without a reload (progress rises, new points appear, frames with their fitted lines, the
results at the end), on a phone-sized screen. A screenshot is kept under pytest's tmp path."""

from __future__ import annotations

import os
import sqlite3

import pytest

from tests._serve_helpers import instrument_run, instrument_serve, short_iso

CHROMIUM = os.environ.get("INSTRUMENT_CHROMIUM", "/usr/bin/chromium")
# What Chromium needs on this machine (root, no GPU, a closed network): see docs/web_view.md.
CHROMIUM_FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]

pytestmark = [pytest.mark.timeout(300), pytest.mark.slow]


@pytest.fixture
def browser():
    """Debian's Chromium through Playwright; skipped, with the reason, only where none can be had."""
    sync_api = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
    if not (os.path.isfile(CHROMIUM) and os.access(CHROMIUM, os.X_OK)):
        pytest.skip(f"no Chromium at {CHROMIUM} (install Debian's chromium package; .ci/run does)")
    with sync_api.sync_playwright() as playwright:
        # A Chromium that is there but does not start is a failure, not a skip. Playwright gives
        # it a new empty profile of its own.
        instance = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_FLAGS)
        try:
            yield instance
        finally:
            instance.close()


def _done(page) -> int:
    return int(page.text_content("#done") or 0)


def _points(page) -> int:
    return int(page.evaluate("document.querySelectorAll('#scatter circle.pt').length"))


def test_live_page_follows_a_simulated_run_without_reloading(browser, tmp_path):
    runs = tmp_path / "runs"
    procedure = short_iso(tmp_path, cycles=4)
    with instrument_serve(runs) as endpoints:
        page = browser.new_page(viewport={"width": 390, "height": 844})  # a phone
        page.goto(endpoints["web"] + "live")
        page.evaluate("window.sameDocument = true")  # gone if the page reloads
        with instrument_run(runs, procedure, tmp_path / "run.log") as run:
            # The cell starts, the dry run passes, then the first pose lands on the page by itself.
            page.wait_for_function("Number(document.getElementById('done').textContent) >= 1", timeout=150_000)
            done, points = _done(page), _points(page)
            page.wait_for_function(
                f"Number(document.getElementById('done').textContent) > {done}"
                f" && document.querySelectorAll('#scatter circle.pt').length > {points}", timeout=60_000)
            assert _done(page) > done and _points(page) > points
            assert page.text_content("#total") == "25"

            # The three latest frames, each with its two fitted stripe lines and the cross marked.
            page.wait_for_function("document.querySelectorAll('#frames svg line.stripe').length === 6", timeout=60_000)
            assert page.locator("#frames svg circle.cross").count() == 3
            # The image the page shows is served, as a PNG. Under load the run may move on between reading
            # the page and asking: the older frames are removed then (404), and the page must have moved on
            # to newer ones (a page left showing removed frames times out here), which are asked for instead.
            for _ in range(5):
                image = page.locator("#frames svg image").first.get_attribute("href")
                answer = page.request.get(endpoints["web"].rstrip("/") + image)
                if answer.status != 404:
                    break
                page.wait_for_function("href => document.querySelector('#frames svg image').getAttribute('href')"
                                       " !== href", arg=image, timeout=30_000)
            assert answer.status == 200 and answer.headers["content-type"] == "image/png"

            page.wait_for_function("document.querySelector('#state .state').textContent === 'FINISHED'",
                                   timeout=150_000)
            assert run.wait(60) == 0
        page.wait_for_function("document.querySelectorAll('#results tr').length === 6", timeout=30_000)
        assert _done(page) == 25
        assert page.locator("#scatter figure").count() == 5  # P1…P5
        assert page.evaluate("window.sameDocument") is True
        # Phone-sized: nothing wider than the screen.
        assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth + 1")

        # The page's figures are the stored run's.
        with sqlite3.connect(runs / "runs.sqlite") as db:
            stored = db.execute("SELECT COUNT(*) FROM samples").fetchone()[0]
        assert stored == 25
        screenshot = tmp_path / "live-page.png"
        page.screenshot(path=str(screenshot), full_page=True)
        print(f"screenshot of the live page: {screenshot}")
        page.close()


def test_runs_list_and_robot_page_update_without_reloading(browser, tmp_path):
    runs = tmp_path / "runs"
    procedure = short_iso(tmp_path, cycles=2, save_frames="never")
    with instrument_serve(runs) as endpoints:
        page = browser.new_page(viewport={"width": 390, "height": 844})
        page.goto(endpoints["web"])
        page.evaluate("window.sameDocument = true")
        assert page.locator("#runs tbody tr").count() == 0
        with instrument_run(runs, procedure, tmp_path / "run.log") as run:
            page.wait_for_selector("#runs tbody tr", timeout=150_000)
            assert run.wait(150) == 0
        page.wait_for_function("document.querySelector('#runs tbody .state').textContent === 'FINISHED'",
                               timeout=30_000)
        page.fill("#search", "no such run")
        page.wait_for_function("document.querySelectorAll('#runs tbody tr').length === 0", timeout=10_000)
        assert page.evaluate("window.sameDocument") is True
        page.goto(endpoints["web"] + "robots")
        page.wait_for_function("document.querySelectorAll('#chart circle.rp').length === 5", timeout=30_000)
        # The run recorded the robot its controller named (the UR twin answers like a UR5): grouped by serial.
        assert "Universal Robots UR5 serial" in (page.text_content("#robots") or "")
        page.close()


def test_live_page_shows_the_pose_stream_of_a_run_measured_in_motion(browser, tmp_path):
    import json

    runs = tmp_path / "runs"
    procedure = tmp_path / "stabilisation.yaml"
    procedure.write_text("procedure: iso9283_stabilisation\nparameters: {cycles: 2, speeds_percent: [100], "
                         "window_s: 0.3, rest_s: 0.2}\n", encoding="utf-8")
    with instrument_serve(runs) as endpoints:
        page = browser.new_page(viewport={"width": 390, "height": 844})
        page.goto(endpoints["web"] + "live")
        page.evaluate("window.sameDocument = true")
        with instrument_run(runs, procedure, tmp_path / "run.log") as run:
            page.wait_for_selector("#posestream svg polyline.distance", timeout=150_000)
            page.wait_for_function("document.querySelector('#state .state').textContent === 'FINISHED'",
                                   timeout=150_000)
            assert run.wait(60) == 0
        page.wait_for_function("document.querySelector('#posestream svg').dataset.step === '1'", timeout=30_000)
        events = [json.loads(line) for line in (tmp_path / "run.log").read_text().splitlines() if line.startswith("{")]
        run_id = events[-1]["run_id"]
        answer = page.request.get(endpoints["web"] + f"api/runs/{run_id}/posestream").json()
        drawn = page.get_attribute("#posestream svg polyline.distance", "points") or ""
        assert answer["step"] == 1 and len(drawn.split()) == len(answer["t"]) == answer["poses"] > 20
        assert page.locator("#posestream svg line.done").count() == 1  # the robot's done signal marked
        assert page.evaluate("window.sameDocument") is True
        # The --jsonl stream events of the same run: one per streamed second at least, SI.
        live = [e for e in events if e.get("event") == "stream"]
        assert len(live) >= 2 and all(len(e["pose"]) == 6 and e["rate_hz"] == 100.0 for e in live)
        assert all(e["distance_to_target"] < 0.01 for e in live)  # within 10 mm of the commanded pose
        page.close()
