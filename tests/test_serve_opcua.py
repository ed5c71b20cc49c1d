"""The OPC UA server with asyncua's own client: a client starts a short simulated run, follows its
progress by subscription and reads the results, which must be the stored run's and agree with the
twins' ground truth; pause, resume and abort drive the run as documented."""

from __future__ import annotations

import asyncio
import json
import sqlite3
import time
from pathlib import Path

import pytest
from asyncua import Client, ua
from asyncua.ua.uaerrors import BadInvalidState

from procedures.serve import NAMESPACE
from tests._serve_helpers import instrument_serve, short_iso

# asyncua's client probes the server every watchdog interval and gives up on the connection when one
# probe takes longer than that (1 s by default): a loaded host's server may take longer to answer.
WATCHDOG_S = 10.0

pytestmark = [pytest.mark.timeout(300), pytest.mark.slow]


class Cell:
    """The test's cell controller: a connected client and the instrument's nodes by path."""

    def __init__(self, client: Client, index: int) -> None:
        self.client, self.index = client, index
        self.changes: dict[str, list] = {}

    def node(self, path: str):
        return self.client.get_node(ua.NodeId(f"Instrument{'.' + path if path else ''}", self.index))

    async def read(self, path: str):
        return await self.node(path).read_value()

    async def call(self, method: str, *args: str):
        return await self.node("").call_method(ua.QualifiedName(method, self.index), *args)

    async def wait_for(self, path: str, accept, timeout: float):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            value = await self.read(path)
            if accept(value):
                return value
            await asyncio.sleep(0.2)
        raise AssertionError(f"{path} still {value!r} after {timeout} s")

    def datachange_notification(self, node, value, data) -> None:  # asyncua's subscription handler
        self.changes.setdefault(node.nodeid.Identifier, []).append(value)

    def status_change_notification(self, status) -> None:  # asyncua's handler, for a subscription's status
        self.changes.setdefault("status", []).append(status)


async def _connected(url: str, body) -> None:
    async with Client(url, timeout=30, watchdog_intervall=WATCHDOG_S) as client:
        cell = Cell(client, await client.get_namespace_index(NAMESPACE))
        await body(cell)


def _stored(runs: Path, run_id: str) -> tuple[dict, list[dict]]:
    with sqlite3.connect(runs / "runs.sqlite") as db:
        state, results = db.execute("SELECT state, results FROM runs WHERE id = ?", (run_id,)).fetchone()
        samples = [json.loads(row[0] or row[1]) for row in db.execute(
            "SELECT corrected, solved FROM samples WHERE run_id = ? ORDER BY step_index", (run_id,))]
    return {"state": state, "results": json.loads(results) if results else None}, samples


def test_a_cell_starts_a_run_follows_progress_and_reads_the_results(tmp_path):
    runs = tmp_path / "runs"
    procedure = short_iso(tmp_path, cycles=2, save_frames="never")

    async def body(cell: Cell) -> None:
        assert await cell.read("State") == "IDLE"
        subscription = await cell.client.create_subscription(50, cell)
        await subscription.subscribe_data_change([cell.node("Progress.Done"), cell.node("State")])
        with pytest.raises(BadInvalidState):
            await cell.call("StartRun", "no_such_procedure", "sim", "")
        assert "no_such_procedure" in await cell.read("LastMessage")
        with pytest.raises(BadInvalidState):
            await cell.call("StartRun", str(procedure), "sim", "cycles=1")  # the procedure's own check: ≥ 2
        assert "cycles" in await cell.read("LastMessage")

        await cell.call("StartRun", str(procedure), "sim", "cycles=3")  # the override makes it 5 + 15 poses
        assert await cell.read("State") == "STARTING"
        await cell.wait_for("State", lambda s: s in ("FINISHED", "FAILED", "ABORTED"), 180)
        assert await cell.read("State") == "FINISHED", await cell.read("Reason")
        run_id = await cell.read("RunId")
        assert await cell.read("Progress.Total") == await cell.read("Progress.Done") == 20
        await cell.wait_for("Progress.Done", lambda d: d == 20, 5)
        await asyncio.sleep(0.5)  # the last notifications of the subscription
        done = cell.changes["Instrument.Progress.Done"]
        assert done[-1] == 20 and len(done) >= 10 and done == sorted(done)  # followed pose by pose, never back
        assert "RUNNING" in cell.changes["Instrument.State"]

        stored, samples = _stored(runs, run_id)
        assert stored["state"] == "FINISHED"
        assert await cell.read("LastPose.Pose") == pytest.approx(samples[-1]["pose"])
        assert await cell.read("Results.RunId") == run_id
        assert json.loads(await cell.read("Results.Json")) == stored["results"]
        for label in ("P1", "P2", "P3", "P4", "P5"):
            point = stored["results"]["points"][label]
            rp_l = await cell.read(f"Results.{label}.RP_l")
            low, high = await cell.read(f"Results.{label}.RP_l_CI")
            assert await cell.read(f"Results.{label}.N") == point["n"] == 3
            assert rp_l == pytest.approx(point["stats"]["rp_l"]) and low <= rp_l <= high
            assert await cell.read(f"Results.{label}.RP_a") == pytest.approx(point["stats"]["rp_a"])
            # The twins' ground truth: the same poses as the cell really attained them, within the
            # simulated optics' per-frame noise (~1 µm per component) at n = 3.
            assert rp_l == pytest.approx(point["true_stats"]["rp_l"], abs=8e-6)
        assert await cell.read("Alarms.Active") is False

    with instrument_serve(runs, "--opcua", "--opcua-port", "0") as endpoints:
        asyncio.run(_connected(endpoints["opcua"], body))


def test_pause_resume_and_abort_follow_the_run_store(tmp_path):
    runs = tmp_path / "runs"
    procedure = short_iso(tmp_path, cycles=8, save_frames="never")

    async def body(cell: Cell) -> None:
        await cell.call("StartRun", str(procedure), "sim", "")
        await cell.wait_for("Progress.Done", lambda d: d >= 2, 180)
        await cell.call("Pause")
        await cell.wait_for("State", lambda s: s == "PAUSED", 60)
        run_id = await cell.read("RunId")
        paused_at = await cell.read("Progress.Done")
        assert _stored(runs, run_id)[0]["state"] == "PAUSED"
        with pytest.raises(BadInvalidState):
            await cell.call("StartRun", str(procedure), "sim", "")  # resume or abort the paused run first
        assert "PAUSED" in await cell.read("LastMessage")
        await cell.call("Resume")
        await cell.wait_for("Progress.Done", lambda d: d > paused_at, 180)
        assert await cell.read("State") == "RUNNING" and await cell.read("RunId") == run_id
        await cell.call("Abort")
        await cell.wait_for("State", lambda s: s == "ABORTED", 60)
        stored, samples = _stored(runs, run_id)
        assert stored["state"] == "ABORTED"
        assert paused_at < len(samples) < 45  # nothing measured twice (the store's key), nothing after the abort
        assert await cell.read("Alarms.Active") is True

    with instrument_serve(runs, "--opcua", "--opcua-port", "0") as endpoints:
        asyncio.run(_connected(endpoints["opcua"], body))
