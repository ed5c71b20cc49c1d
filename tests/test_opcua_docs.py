"""docs/opcua.md names the nodes the server really has: every variable its table names (with ``<P>`` a point
of a finished ISO run) is read by its string node id from a running ``instrument serve --opcua``, and every
variable the server declares is in the table. A name a PLC copies from the document must never answer
BadNodeIdUnknown."""

from __future__ import annotations

import asyncio
import re
from pathlib import Path

import numpy as np
import pytest
from asyncua import Client, ua

from procedures.serve import NAMESPACE
from procedures.station import InstrumentScience
from procedures.store import RunState, RunStore
from tests._serve_helpers import instrument_serve

# asyncua's client probes the server every watchdog interval and gives up on the connection when one
# probe takes longer than that (1 s by default): a loaded host's server may take longer to answer.
WATCHDOG_S = 10.0

pytestmark = [pytest.mark.timeout(300), pytest.mark.integration]

DOC = Path(__file__).resolve().parents[1] / "docs" / "opcua.md"


def documented_variables() -> list[str]:
    """The node paths of the document's variables table (``Results.<P>.RP_l`` kept with its ``<P>``); a cell
    like ``Results.<P>.RP_l``, ``RP_a`` names its siblings by their last part; ``…`` stands for more."""
    text = DOC.read_text(encoding="utf-8")
    table = text.split("## Variables", 1)[1].split("\n## ", 1)[0]
    paths: list[str] = []
    for line in table.splitlines():
        cells = line.split("|")
        if len(cells) < 3 or not cells[1].strip().startswith("`"):
            continue
        names = re.findall(r"`([^`]+)`", cells[1])
        prefix = names[0].rpartition(".")[0]
        for name in names:
            paths.append(name if "." in name or not prefix else f"{prefix}.{name}")
    return paths


def test_the_document_lists_the_fixed_variables_and_the_point_figures():
    paths = documented_variables()
    assert {"State", "Progress.Done", "Results.<P>.RP_l", "Results.<P>.AP_P", "Results.<P>.AP_P_CI",
            "Results.<P>.AP_P_U", "Alarms.Time"} <= set(paths)


def test_every_documented_node_is_in_the_servers_address_space(tmp_path):
    runs = tmp_path / "runs"
    rng = np.random.default_rng(3)
    commanded = np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0])
    stats = InstrumentScience().iso_statistics(commanded + rng.normal(0.0, 1e-5, (30, 6)), commanded)
    figures = {key: {"value": stats[key], "expanded_uncertainty": 1e-6} for key in ("rp_l", "rp_a", "ap_p", "ap_x")}
    with RunStore(runs) as store:  # a finished ISO run whose results carry every statistic and some U
        run_id = store.create_run(procedure="iso9283_repeatability", parameters={"cycles": 30}, station={},
                                  software_version="t", station_name="cell")
        store.set_state(run_id, RunState.FINISHED)
        store.set_results(run_id, {"kind": "iso9283", "order": ["P1"], "points": {"P1": {"n": 30, "stats": stats}},
                                   "figures": {"points": {"P1": figures}}})

    async def read_all(url: str) -> tuple[dict[str, str], list[str]]:
        problems: dict[str, str] = {}
        declared: list[str] = []
        async with Client(url, timeout=30, watchdog_intervall=WATCHDOG_S) as client:
            index = await client.get_namespace_index(NAMESPACE)

            async def read(path: str):
                return await client.get_node(ua.NodeId(f"Instrument.{path}", index)).read_value()

            for _ in range(100):  # the results nodes appear once the server has read the finished run
                if await read("Results.RunId") == run_id:
                    break
                await asyncio.sleep(0.2)
            for documented in documented_variables():
                if "…" in documented:
                    continue
                path = documented.replace("<P>", "P1")
                try:
                    await read(path)
                except ua.UaStatusCodeError as exc:
                    problems[path] = type(exc).__name__

            async def browse(node) -> None:  # every variable below Instrument, by its string id
                for child in await node.get_children():
                    identifier = child.nodeid.Identifier
                    if not (isinstance(identifier, str) and identifier.startswith("Instrument.")):
                        continue  # a method's argument list
                    if await child.read_node_class() == ua.NodeClass.Variable:
                        declared.append(identifier.removeprefix("Instrument."))
                    elif child.nodeid.NamespaceIndex == index:
                        await browse(child)

            await browse(client.get_node(ua.NodeId("Instrument", index)))
        return problems, declared

    with instrument_serve(runs, "--opcua", "--opcua-port", "0") as endpoints:
        problems, declared = asyncio.run(read_all(endpoints["opcua"]))
    assert problems == {}  # what the document names, the server has
    fixed = [path for path in declared if not re.match(r"Results\.P\d\.", path)]
    assert len(fixed) > 20
    assert sorted(set(fixed) - set(documented_variables())) == []  # and what the server has, the document names


def test_start_run_passes_overrides_as_set_and_writes_no_procedure_copy(tmp_path):
    """StartRun's overrides reach the run as ``instrument run --set`` (stored with it: its parameters and its
    title); a refused StartRun leaves nothing behind, an accepted one only its process's log."""
    from procedures.serve import LaunchRefused, RunLauncher

    runs = tmp_path / "runs"

    async def body() -> None:
        launcher = RunLauncher(runs)
        try:
            for overrides in ("cycles=1", "cyclez=3", "cycles"):
                with pytest.raises(LaunchRefused):
                    await launcher.start_run("iso9283_repeatability", "sim", overrides)
            assert not (runs / "serve").exists() or list((runs / "serve").iterdir()) == []
            launch = await launcher.start_run("iso9283_repeatability", "sim", "cycles=3; settle_time_s=0")
            for _ in range(900):  # until the run is in the store; closing the launcher then aborts it
                if launch.run_id is not None or not launch.alive:
                    break
                await asyncio.sleep(0.2)
            assert launch.run_id is not None
        finally:
            await launcher.close()

    asyncio.run(body())
    assert [path.suffix for path in (runs / "serve").iterdir()] == [".log"]  # no procedure copy
    with RunStore(runs) as store:
        (row,) = store.list_runs()
        run = store.get_run(row["id"])
    assert run["parameters"]["cycles"] == 3 and run["parameters"]["settle_time_s"] == 0
    assert run["procedure_text"].startswith(
        "# iso9283_repeatability.yaml run with --set cycles=3 --set settle_time_s=0")
