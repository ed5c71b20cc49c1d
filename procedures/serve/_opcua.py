"""The OPC UA server for the robot cell (asyncua): the instrument's state, progress, last pose,
last results and alarms, and the methods StartRun, Pause, Resume, Abort.

Every variable follows the run store (read through ``StoreReader``, refreshed when the store changes);
the methods drive runs through ``RunLauncher`` (child ``instrument run`` processes). Node ids are
strings in the instrument's namespace (``ns=<index of NAMESPACE>;s=Instrument.Progress.Done``), so a
PLC can address them without browsing. Units are SI (m, rad, s). Table: docs/opcua.md.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import json
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from asyncua import Node, Server, ua

from procedures.report import iso_points
from procedures.serve._launcher import LaunchRefused, RunLauncher
from procedures.serve._reader import StoreReader

NAMESPACE = "urn:opr-repeatability:instrument"
ROOT = "Instrument"
V = ua.VariantType


@dataclass(frozen=True)
class OpcUaSettings:
    """host, port : the endpoint (loopback); poll_interval_s : how often the store's change counter is read."""

    host: str = "127.0.0.1"
    port: int = 4840
    poll_interval_s: float = 0.25

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://{self.host}:{self.port}/opr/instrument/"


# (node path below Instrument, variant type, initial value, description)
VARIABLES: tuple[tuple[str, ua.VariantType, Any, str], ...] = (
    ("State", V.String, "IDLE", "IDLE, STARTING, QUEUED, RUNNING, PAUSING, PAUSED, FINISHED, FAILED or ABORTED"),
    ("RunId", V.String, "", "the current run (the one started here, else the newest active or newest run)"),
    ("Procedure", V.String, "", "its procedure kind"),
    ("Title", V.String, "", "its title, from the parameters in force (a run with --set cycles=3: '... 3 cycles')"),
    ("Station", V.String, "", "its station name"),
    ("Reason", V.String, "", "why it paused, failed or was aborted"),
    ("LastMessage", V.String, "", "the outcome of the last method call, one line"),
    ("Progress.Done", V.UInt32, 0, "committed poses"),
    ("Progress.Total", V.UInt32, 0, "planned poses"),
    ("Progress.Fraction", V.Double, 0.0, "Done / Total"),
    ("Progress.Phase", V.String, "", "phase of the newest pose (transform, iso, calibration ...)"),
    ("Progress.Cycle", V.Int32, -1, "ISO cycle of the newest pose, from 0 (-1: none)"),
    ("Progress.EtaSeconds", V.Double, -1.0, "time to the end at the pace of the last 20 poses, s (-1: unknown)"),
    ("LastPose.Pose", V.Double, [math.nan] * 6,
     "x, y, z (m), a, b, c (rad) of the OPR in M, corrected when the run corrects"),
    ("LastPose.Step", V.String, "", "step key of the newest pose"),
    ("LastPose.Label", V.String, "", "its point label"),
    ("LastPose.Ok", V.Boolean, False, "whether it was measured"),
    ("LastPose.ResidualRms", V.Double, math.nan, "pose solver residual, m"),
    ("LastPose.Error", V.String, "", "why it failed"),
    ("Results.RunId", V.String, "", "the newest finished run with results"),
    ("Results.Procedure", V.String, "", "its procedure kind"),
    ("Results.Json", V.String, "", "its whole results document (JSON, SI)"),
    ("Alarms.Active", V.Boolean, False, "the current run failed or was aborted, or a run process died"),
    ("Alarms.LastError", V.String, "", "the failure's reason, one line"),
    ("Alarms.Time", V.DateTime, dt.datetime(1601, 1, 1, tzinfo=dt.UTC), "when the alarm was raised (1601: never)"),
)


def _argument(name: str, description: str) -> ua.Argument:
    argument = ua.Argument()
    argument.Name = name
    argument.DataType = ua.NodeId(ua.Int32(ua.ObjectIds.String))
    argument.ValueRank = -1
    argument.ArrayDimensions = []
    argument.Description = ua.LocalizedText(description)
    return argument


def opc_name(stat: str) -> str:
    """``rp_l`` → ``RP_l``, ``rp_l_ci`` → ``RP_l_CI``, ``rp_l_u`` → ``RP_l_U``, ``ap_p`` → ``AP_P``, ``n`` → ``N``
    (the ISO 9283 symbols: positional accuracy is AP_P, its components AP_x … AP_c)."""
    parts = stat.split("_")
    if parts[0] in ("rp", "ap", "s"):
        parts[0] = parts[0].upper()
    if parts[:2] == ["AP", "p"]:
        parts[1] = "P"
    if parts[-1] in ("ci", "u"):
        parts[-1] = parts[-1].upper()
    return "_".join(parts) if len(parts) > 1 else stat.upper()


class InstrumentOpcUa:
    """The server. ``await start()``, then it follows the store until ``await stop()``.

    Parameters
    ----------
    reader : the run store
    launcher : starts and controls runs for the methods
    settings : endpoint and polling
    """

    def __init__(self, reader: StoreReader, launcher: RunLauncher, settings: OpcUaSettings) -> None:
        self.reader, self.launcher, self.settings = reader, launcher, settings
        self.server = Server()
        self.nodes: dict[str, Node] = {}
        self._values: dict[str, Any] = {}
        self._points: dict[str, dict[str, Node]] = {}
        self._idx = 0
        self._task: asyncio.Task[None] | None = None
        self._alarm_from_launcher: str | None = None
        self._wake = asyncio.Event()
        launcher.on_problem = self._launcher_problem

    @property
    def endpoint(self) -> str:
        """The endpoint URL with the port actually bound (``port`` 0 picks a free one)."""
        port = self.server.bserver.port if self.server.bserver is not None else self.settings.port
        return f"opc.tcp://{self.settings.host}:{port}/opr/instrument/"

    async def start(self) -> None:
        logging.getLogger("asyncua").setLevel(logging.ERROR)  # its INFO lines would flood the console
        await self.server.init()
        self.server.set_endpoint(self.settings.endpoint)
        self.server.set_server_name("OPR repeatability instrument")
        self.server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        self._idx = await self.server.register_namespace(NAMESPACE)
        root = await self.server.nodes.objects.add_object(self._node_id(ROOT), ua.QualifiedName(ROOT, self._idx))
        self.nodes[""] = root
        for path, vtype, initial, description in VARIABLES:
            await self._variable(path, vtype, initial, description)
        for name, handler, inputs, description in (
            ("StartRun", self._start_run, [_argument("Procedure", "built-in name or procedure file"),
                                           _argument("Station", "station file, or 'sim' for the simulated cell"),
                                           _argument("Overrides", "key=value pairs separated by ';' (may be empty)")],
             "start a run (refused while one started here is going)"),
            ("Pause", self._pause, [], "pause the current run at its next safe point (it is left PAUSED)"),
            ("Resume", self._resume, [], "continue the current PAUSED (or interrupted) run"),
            ("Abort", self._abort, [], "abort the current run: robot and table stopped, ABORTED stored"),
        ):
            method = await root.add_method(self._node_id(f"{ROOT}.{name}"), ua.QualifiedName(name, self._idx),
                                           handler, inputs, [])
            await method.write_attribute(ua.AttributeIds.Description,
                                         ua.DataValue(ua.Variant(ua.LocalizedText(description))))
        await self.server.start()
        self._task = asyncio.create_task(self._follow_store())

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        await self.launcher.close()
        await self.server.stop()

    # ------------------------------------------------------------------------------ the nodes
    def _node_id(self, name: str) -> ua.NodeId:
        """``ns=<instrument namespace>;s=<name>``: stable string ids a PLC can use without browsing."""
        return ua.NodeId(ua.String(name), ua.Int16(self._idx))

    async def _parent(self, path: str) -> Node:
        """The object that holds ``path`` (``Progress.Done`` → the ``Progress`` object), made on first use."""
        parent_path = path.rpartition(".")[0]
        if parent_path in self.nodes:
            return self.nodes[parent_path]
        grand = await self._parent(parent_path)
        name = parent_path.rpartition(".")[2]
        node = await grand.add_object(self._node_id(f"{ROOT}.{parent_path}"), ua.QualifiedName(name, self._idx))
        self.nodes[parent_path] = node
        return node

    async def _variable(self, path: str, vtype: ua.VariantType, initial: Any, description: str) -> Node:
        parent = await self._parent(path)
        node = await parent.add_variable(self._node_id(f"{ROOT}.{path}"),
                                         ua.QualifiedName(path.rpartition(".")[2], self._idx),
                                         ua.Variant(initial, vtype))
        await node.write_attribute(ua.AttributeIds.Description, ua.DataValue(ua.Variant(ua.LocalizedText(description))))
        self.nodes[path] = node
        self._values[path] = initial
        return node

    async def _set(self, path: str, value: Any) -> None:
        """Write a variable only when its value changed (every write notifies the subscribers)."""
        if _same(self._values.get(path), value):
            return
        node = self.nodes[path]
        vtype = await node.read_data_type_as_variant_type()
        await node.write_value(ua.Variant(value, vtype))
        self._values[path] = value

    # ---------------------------------------------------------------------- following the store
    async def _follow_store(self) -> None:
        seen = None
        while True:
            try:
                version = await asyncio.to_thread(self.reader.version)
                launcher_state = (self.launcher.starting, self.launcher.active is not None, self._alarm_from_launcher)
                if (version, launcher_state) != seen:
                    seen = (version, launcher_state)
                    await self.refresh()
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # the store busy or replaced for a moment: say so, try again
                await self._set("LastMessage", f"cannot read the run store: {exc}")
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake.wait(), self.settings.poll_interval_s)
            self._wake.clear()

    def _current_run_id(self) -> str | None:
        active = self.launcher.active
        if active is not None and active.run_id is not None:
            return active.run_id
        return self.reader.current_run_id()

    async def refresh(self) -> None:
        """Read the store and update every variable that changed."""
        run_id = await asyncio.to_thread(self._current_run_id)
        snap = await asyncio.to_thread(self.reader.snapshot, run_id) if run_id else None
        run = snap["run"] if snap else None
        state = "STARTING" if self.launcher.starting else (run["state"] if run else "IDLE")
        active = self.launcher.active
        if state == "PAUSED" and active is not None and run is not None and active.run_id == run["id"]:
            state = "PAUSING"  # stored PAUSED, but its process is still bringing the cell to rest
        await self._results()  # before State: a client that sees FINISHED finds the run's results in place
        await self._set("State", state)
        await self._set("RunId", run["id"] if run else "")
        await self._set("Procedure", run["procedure"] if run else "")
        await self._set("Title", run["title"] if run else "")
        await self._set("Station", (run["station"] or "") if run else "")
        await self._set("Reason", (run["reason"] or "") if run else "")
        done, total = (run["done"] or 0, run["total"] or 0) if run else (0, 0)
        await self._set("Progress.Done", done)
        await self._set("Progress.Total", total)
        await self._set("Progress.Fraction", done / total if total else 0.0)
        await self._set("Progress.Phase", (run.get("phase") or "") if run else "")
        cycle = run.get("cycle") if run else None
        await self._set("Progress.Cycle", int(cycle) if cycle is not None else -1)
        eta = run.get("eta_s") if run else None
        await self._set("Progress.EtaSeconds", float(eta) if eta is not None else -1.0)
        last = snap["points"][-1] if snap and snap["points"] else None
        if last is not None:
            await self._set("LastPose.Pose", [float(v) for v in (last["pose"] or [math.nan] * 6)])
            await self._set("LastPose.Step", last["key"])
            await self._set("LastPose.Label", last["label"] or "")
            await self._set("LastPose.Ok", bool(last["ok"]))
            residual = last["residual_rms"]
            await self._set("LastPose.ResidualRms", float(residual) if residual is not None else math.nan)
            await self._set("LastPose.Error", last["error"] or "")
        await self._alarms(run)

    async def _alarms(self, run: dict[str, Any] | None) -> None:
        failed = run is not None and run["state"] in ("FAILED", "ABORTED")
        message = self._alarm_from_launcher or ((run["reason"] or run["state"]) if failed and run else "")
        active = bool(message)
        if active and not self._values.get("Alarms.Active"):
            await self._set("Alarms.Time", dt.datetime.now(dt.UTC))
        await self._set("Alarms.Active", active)
        if active:
            await self._set("Alarms.LastError", message.splitlines()[0])

    async def _results(self) -> None:
        finished = next((r for r in await asyncio.to_thread(self.reader.runs) if r["state"] == "FINISHED"), None)
        if finished is None or finished["id"] == self._values.get("Results.RunId"):
            return
        results = (await asyncio.to_thread(self.reader.run, finished["id"])).get("results") or {}
        for label, figures in iso_points(results).items():
            for stat, value in figures.items():
                if stat == "error":
                    continue
                path = f"Results.{label}.{opc_name(stat)}"
                if path not in self.nodes:
                    initial = [math.nan, math.nan] if isinstance(value, list) else (0 if stat == "n" else math.nan)
                    await self._variable(path, V.UInt32 if stat == "n" else V.Double, initial,
                                         f"{stat} of point {label} (SI: m, rad; _CI: 95 % interval; "
                                         "_U: expanded uncertainty, k = 2)")
                await self._set(path, _number(value, stat))
        await self._set("Results.Json", json.dumps(results, allow_nan=True))
        await self._set("Results.Procedure", finished["procedure"])
        await self._set("Results.RunId", finished["id"])  # last: a client seeing the id finds the figures written

    def _launcher_problem(self, message: str) -> None:
        self._alarm_from_launcher = message
        self._wake.set()

    # ---------------------------------------------------------------------------------- methods
    async def _call(self, name: str, action: Callable[[], Any]) -> list[ua.Variant] | ua.StatusCode:
        try:
            result = action()
            if asyncio.iscoroutine(result):
                await result
        except LaunchRefused as exc:  # the client gets BadInvalidState, LastMessage says why
            await self._set("LastMessage", f"{name} refused: {exc}")
            return ua.StatusCode(ua.UInt32(ua.StatusCodes.BadInvalidState))
        await self._set("LastMessage", f"{name}: accepted")
        await self.refresh()  # State reads STARTING (or the new state) as soon as the call returns
        return []

    async def _start_run(self, parent: ua.NodeId, procedure: ua.Variant, station: ua.Variant,
                         overrides: ua.Variant) -> list[ua.Variant] | ua.StatusCode:
        await self.refresh()

        def start() -> Any:
            if self._values.get("State") == "PAUSED":
                raise LaunchRefused(f"run {self._values.get('RunId')} is PAUSED; resume or abort it first")
            self._alarm_from_launcher = None
            return self.launcher.start_run(str(procedure.Value or ""), str(station.Value or ""),
                                           str(overrides.Value or ""))
        return await self._call("StartRun", start)

    async def _pause(self, parent: ua.NodeId) -> list[ua.Variant] | ua.StatusCode:
        return await self._call("Pause", self.launcher.pause)

    async def _resume(self, parent: ua.NodeId) -> list[ua.Variant] | ua.StatusCode:
        run_id = await asyncio.to_thread(self._current_run_id)

        def resume() -> Any:
            if run_id is None or self._values.get("State") not in ("PAUSED", "RUNNING", "QUEUED", "FAILED"):
                raise LaunchRefused(f"the current run is {self._values.get('State')}; only a paused or "
                                    "interrupted run can be resumed")
            return self.launcher.resume(run_id)
        return await self._call("Resume", resume)

    async def _abort(self, parent: ua.NodeId) -> list[ua.Variant] | ua.StatusCode:
        run_id = await asyncio.to_thread(self._current_run_id)
        paused = run_id if self._values.get("State") == "PAUSED" else None
        return await self._call("Abort", lambda: self.launcher.abort(paused))


def _number(value: Any, stat: str) -> Any:
    if isinstance(value, list):
        return [float(v) if v is not None else math.nan for v in value]
    if stat == "n":
        return int(value or 0)
    return float(value) if value is not None else math.nan


def _same(a: Any, b: Any) -> bool:
    """Equality that treats NaN as equal to NaN (an unknown value stays unknown, no new notification)."""
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return bool(a == b) and type(a) is type(b)
