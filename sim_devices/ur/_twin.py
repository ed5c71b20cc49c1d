"""``URControllerTwin``: a UR e-Series controller on one loopback address, and its process host.

The twin binds the fixed UR ports (RTDE 30004, dashboard 29999, script 30003) on a configurable
127.0.0.x address, so tests and cells give each twin its own address. It must run in another process
than the ur_rtde client (the client's constructors hold the GIL while they wait): use
``TwinProcess("sim_devices.ur:standalone_host", {...})`` or ``python -m sim_devices.ur``.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from sim_devices.control import dispatch
from sim_devices.faults import FaultKind, FaultPlan, fault_kind
from sim_devices.ur._config import URTwinConfig
from sim_devices.ur._controller import URController
from sim_devices.ur._servers import (
    DASHBOARD_PORT,
    RTDE_PORT,
    SCRIPT_PORT,
    DashboardHandler,
    InputOwnership,
    RTDEHandler,
    RTDEStreams,
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
        self.streams_hub = RTDEStreams(self.controller)
        self.servers = {
            "rtde": TcpServer(host, ports["rtde"], RTDEHandler(self.controller, InputOwnership(), self.streams_hub),
                              "rtde"),
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
        for server in self.servers.values():  # all at once: each accept loop takes up to 0.2 s to see it
            server.signal_stop()
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
    def state(self) -> dict[str, Any]:
        """The controller's state now (modes, safety bits, joints, TCP pose ...)."""
        return self.controller.describe()

    def visits(self, since: int = 0) -> list[dict[str, Any]]:
        """True attained poses of the finished moves, from index ``since`` on."""
        with self.controller.lock:
            return list(self.controller.visits[int(since):])

    def truth(self, event: str | None = "pose") -> list[dict[str, Any]]:
        """The world's ground-truth log: the settled poses (``event="payload"``: every payload set; None: all)."""
        return self.world.truth.entries(event)

    def events(self) -> list[str]:
        with self.controller.lock:
            return list(self.controller.events)

    def arm_fault(self, kind: FaultKind | str, count: int = 1, **params: Any) -> list[str]:
        """Arm a fault; robot faults fire mid-move at path fraction ``at`` (default 0.5). Returns what is armed."""
        self.faults.arm(kind, int(count), **params)
        return [a.kind.value for a in self.faults.armed()]

    def trigger(self, kind: FaultKind | str) -> dict[str, Any]:
        """Make ``protective_stop``, ``emergency_stop``, ``program_stopped`` or ``disconnect`` happen now."""
        self.controller.trigger(fault_kind(kind))
        return self.controller.describe()

    def clear_faults(self) -> dict[str, Any]:
        """Disarm every fault, end a stream stall and unlock safety stops."""
        self.faults.clear()
        self.controller.stream_stall_until = 0.0
        self.controller.clear_safety()
        return self.controller.describe()

    def fired(self) -> list[tuple[str, dict[str, Any]]]:
        return [(k.value, p) for k, p in self.faults.fired()]

    def set_repeatability(self, translation_std: float | None = None, rotation_std: float | None = None,
                          approach_bias: float | None = None, drift_amplitude: float | None = None,
                          drift_time_constant: float | None = None) -> dict[str, Any]:
        """Change the attained-pose error model from now on (SI units); returns the whole config."""
        cfg = self.config
        changes = {"repeatability_translation_std": translation_std, "repeatability_rotation_std": rotation_std,
                   "approach_bias": approach_bias, "thermal_drift_amplitude": drift_amplitude,
                   "thermal_drift_time_constant": drift_time_constant}
        for field_name, value in changes.items():
            if value is not None:
                setattr(cfg, field_name, float(value))
        return cfg.to_dict()

    def connections(self) -> dict[str, int]:
        return {name: server.connection_count for name, server in self.servers.items()}

    def streams(self) -> list[dict[str, int]]:
        """Each RTDE connection's data packages sent and peak backlog (bytes queued for a slow reader)."""
        return self.streams_hub.stats()

    def describe(self) -> dict[str, Any]:
        return {"config": self.config.to_dict(), "world": self.world.describe(), "endpoints": self.endpoints()}

    def control(self, command: str, /, **kwargs: Any) -> Any:
        """The twin's control API (also reachable through ``TwinProcess.call``): each command is the
        method of that name: ``endpoints``, ``state``, ``visits`` (since), ``truth`` (event), ``events``,
        ``arm_fault`` (kind, count, params), ``trigger`` (kind), ``clear_faults``, ``fired``,
        ``set_repeatability`` (translation_std, rotation_std, approach_bias, drift_amplitude,
        drift_time_constant), ``connections``, ``streams``, ``describe``.
        """
        commands: dict[str, Callable[..., Any]] = {
            "endpoints": self.endpoints, "state": self.state, "visits": self.visits, "truth": self.truth,
            "events": self.events, "arm_fault": self.arm_fault, "trigger": self.trigger,
            "clear_faults": self.clear_faults, "fired": self.fired, "set_repeatability": self.set_repeatability,
            "connections": self.connections, "streams": self.streams, "describe": self.describe,
        }
        return dispatch(commands, command, kwargs, "UR twin")


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
