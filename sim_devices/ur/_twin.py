"""``URControllerTwin``: a UR e-Series controller on one loopback address, and its process host.

The twin binds the fixed UR ports (RTDE 30004, dashboard 29999, script 30003) on a configurable
127.0.0.x address, so tests and cells give each twin its own address. It must run in another process
than the ur_rtde client (the client's constructors hold the GIL while they wait): use
``TwinProcess("sim_devices.ur:standalone_host", {...})`` or ``python -m sim_devices.ur``.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Mapping
from typing import Any

import numpy as np

from sim_devices.faults import FaultKind, FaultPlan
from sim_devices.ur._config import URTwinConfig
from sim_devices.ur._controller import URController
from sim_devices.ur._servers import (
    DASHBOARD_PORT,
    RTDE_PORT,
    SCRIPT_PORT,
    DashboardHandler,
    InputOwnership,
    RTDEHandler,
    ScriptHandler,
    TcpServer,
)
from sim_devices.world import World, WorldConfig


class URControllerTwin:
    """A protocol-level UR controller twin sharing ``world`` with the rest of a simulated cell.

    Parameters
    ----------
    world : World
        The cell's truth; the twin sets the true flange pose in it and starts where it says.
    host : str
        Loopback address to bind (127.0.0.0/8 only).
    config : URTwinConfig or mapping, optional
        Time scale, repeatability, version … (see ``URTwinConfig``).
    faults : FaultPlan, optional
        Shared fault plan (a new one by default).
    ports : mapping, optional
        Override ports (``{"rtde": 0, ...}``) — only for experiments; the real client needs the
        fixed ports.
    """

    def __init__(self, world: World, host: str = "127.0.0.2", config: URTwinConfig | Mapping[str, Any] | None = None,
                 *, faults: FaultPlan | None = None, ports: Mapping[str, int] | None = None) -> None:
        if not ipaddress.ip_address(host).is_loopback:
            raise ValueError(f"UR twin: host must be a loopback address (127.0.0.0/8), got {host!r}")
        self.world = world
        self.host = host
        self.config = config if isinstance(config, URTwinConfig) else URTwinConfig.from_dict(config)
        self.faults = faults or FaultPlan()
        ports = {"rtde": RTDE_PORT, "dashboard": DASHBOARD_PORT, "script": SCRIPT_PORT, **dict(ports or {})}
        self.controller = URController(world, self.config, self.faults, on_disconnect=self.drop_connections)
        self.script_handler = ScriptHandler(self.controller)
        self.servers = {
            "rtde": TcpServer(host, ports["rtde"], RTDEHandler(self.controller, InputOwnership()), "rtde"),
            "dashboard": TcpServer(host, ports["dashboard"], DashboardHandler(self.controller), "dashboard"),
            "script": TcpServer(host, ports["script"], ScriptHandler(self.controller), "script"),
        }
        self.servers["script"].handler = self.script_handler
        self._started = False

    # ----------------------------------------------------------------------------- lifecycle
    def start(self) -> dict[str, Any]:
        """Bind the ports and start the controller; returns the endpoints."""
        started = []
        try:
            for server in self.servers.values():
                server.start()
                started.append(server)
        except OSError as exc:
            for server in started:
                server.stop()
            raise OSError(f"UR twin cannot bind {self.host}: {exc}") from exc
        self.controller.start()
        self._started = True
        return self.endpoints()

    def stop(self) -> None:
        if not self._started:
            return
        self._started = False
        self.controller.stop()
        for server in self.servers.values():
            server.stop()

    def endpoints(self) -> dict[str, Any]:
        return {
            "host": self.host,
            "rtde_port": self.servers["rtde"].port,
            "dashboard_port": self.servers["dashboard"].port,
            "script_port": self.servers["script"].port,
            "version": ".".join(str(v) for v in self.config.version),
            "time_scale": self.config.time_scale,
        }

    def drop_connections(self) -> None:
        for server in self.servers.values():
            server.drop_connections()

    # ----------------------------------------------------------------------------- control API
    def control(self, command: str, **kwargs: Any) -> Any:
        """The twin's control API (also reachable through ``TwinProcess.call``).

        Commands: ``endpoints``; ``state``; ``visits`` (``since``: index) — true attained poses;
        ``truth`` — the world's settled-pose log; ``events``; ``arm_fault`` (``kind``, ``count``,
        params; robot faults fire mid-move at fraction ``at``, default 0.5); ``trigger`` (``kind``:
        protective_stop / emergency_stop / program_stopped / disconnect — now); ``clear_faults``
        (disarm, and unlock safety stops); ``fired``; ``set_repeatability`` (``translation_std``,
        ``rotation_std``, ``approach_bias``, ``drift_amplitude``); ``connections``; ``describe``.
        """
        c = self.controller
        if command == "endpoints":
            return self.endpoints()
        if command == "state":
            return c.describe()
        if command == "visits":
            with c.lock:
                return list(c.visits[int(kwargs.get("since", 0)):])
        if command == "truth":
            return self.world.truth.entries("pose")
        if command == "events":
            with c.lock:
                return list(c.events)
        if command == "arm_fault":
            kind = kwargs.pop("kind")
            count = int(kwargs.pop("count", 1))
            self.faults.arm(kind, count, **kwargs)
            return [a.kind.value for a in self.faults.armed()]
        if command == "trigger":
            c.trigger(FaultKind(kwargs["kind"]))
            return c.describe()
        if command == "clear_faults":
            self.faults.clear()
            c.stream_stall_until = 0.0
            c.clear_safety()
            return c.describe()
        if command == "fired":
            return [(k.value, p) for k, p in self.faults.fired()]
        if command == "set_repeatability":
            cfg = self.config
            mapping = {"translation_std": "repeatability_translation_std", "rotation_std": "repeatability_rotation_std",
                       "approach_bias": "approach_bias", "drift_amplitude": "thermal_drift_amplitude",
                       "drift_time_constant": "thermal_drift_time_constant"}
            for key, value in kwargs.items():
                if key not in mapping:
                    raise ValueError(f"set_repeatability: unknown field {key!r}; expected {sorted(mapping)}")
                setattr(cfg, mapping[key], float(value))
            return cfg.to_dict()
        if command == "connections":
            return {name: server.connection_count for name, server in self.servers.items()}
        if command == "describe":
            return {"config": self.config.to_dict(), "world": self.world.describe(), "endpoints": self.endpoints()}
        raise ValueError(f"UR twin: unknown control command {command!r}")


def standalone_host(host: str = "127.0.0.2", seed: int = 0, time_scale: float = 1.0,
                    world: Mapping[str, Any] | None = None, truth_path: str | None = None,
                    **config: Any) -> URControllerTwin:
    """Factory for ``TwinProcess``: a twin with its own ``World`` (seeded with ``seed`` unless
    ``world`` says otherwise). Extra keyword arguments go to ``URTwinConfig``."""
    world_config = WorldConfig.from_dict({"seed": seed, **dict(world or {})})
    twin_config = URTwinConfig.from_dict({"seed": seed, "time_scale": time_scale, **config})
    return URControllerTwin(World(world_config, truth_path=truth_path), host, twin_config)


def pose_scatter(poses: list[list[float]]) -> dict[str, float]:
    """Helper for tests/benchmarks: per-axis sample std of positions (m) of UR poses."""
    p = np.asarray(poses, dtype=float)[:, :3]
    return {axis: float(s) for axis, s in zip("xyz", p.std(axis=0, ddof=1))}
