"""``ABBControllerTwin``: an IRC5 controller on one loopback address, and its process host.

RWS on ``host:port`` (80 by default, like the controller's WAN port) and the EGM position stream
from ``host`` to the "UCdevice" remote address (default ``host:6510``). Run it in another process
than the clients (``TwinProcess("sim_devices.abb:standalone_host", {...})`` or
``python -m sim_devices.abb``); a cell embeds ``ABBControllerTwin(world, host, config)``.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Callable, Mapping
from typing import Any

from sim_devices.abb._config import ABBTwinConfig
from sim_devices.abb._controller import IRC5, LOCAL_FAULTS
from sim_devices.abb._egm import EgmStream
from sim_devices.abb._rws import RwsServer
from sim_devices.control import dispatch
from sim_devices.faults import FaultKind, FaultPlan, fault_kind
from sim_devices.world import World, WorldConfig

RWS_PORT, EGM_PORT = 80, 6510
#: A comfortable IRB 2600 flange pose (tool0 pointing down, 0.95 m in front, 0.9 m high): the
#: standalone twin's world starts there (the UR cell's reference is beyond axis 3's limit).
IRB2600_REFERENCE_FLANGE = [0.95, 0.0, 0.90, 3.141592653589793, 0.0, 0.0]


class ABBControllerTwin:
    """A protocol-level IRC5 twin sharing ``world`` with the rest of a simulated cell.

    Parameters
    ----------
    world : World
        The cell's truth; the twin sets the true flange pose in it and starts where it says.
    host : str
        Loopback address to bind (127.0.0.0/8 only).
    config : ABBTwinConfig or mapping, optional
        Time scale, repeatability, identity, EGM remote … (see ``ABBTwinConfig``).
    faults : FaultPlan, optional
        Shared fault plan (a new one by default).
    port : int
        The RWS port (0: any free one, reported in ``endpoints()``).
    """

    def __init__(self, world: World, host: str = "127.0.0.2",
                 config: ABBTwinConfig | Mapping[str, Any] | None = None, *, faults: FaultPlan | None = None,
                 port: int = RWS_PORT) -> None:
        if not ipaddress.ip_address(host).is_loopback:
            raise ValueError(f"ABB twin: host must be a loopback address (127.0.0.0/8), got {host!r}")
        self.world = world
        self.host = host
        self.config = config if isinstance(config, ABBTwinConfig) else ABBTwinConfig.from_dict(config)
        self.faults = faults or FaultPlan()
        self.controller = IRC5(world, self.config, self.faults)
        self.rws = RwsServer(self.controller, host, port, self.faults)
        self.controller.arm.on_disconnect = self.rws.drop_connections
        remote = (self.config.egm_remote_host or host, self.config.egm_remote_port)
        every = max(1, round(self.config.egm_sample_rate / self.config.control_period))
        self.egm = EgmStream(host, remote, every, self.config.control_period, lambda: self.controller.arm.tcp_offset,
                             self._egm_state,
                             self.faults)
        self.egm.active = True  # started at power on (EGMStreamStart in the controller's start-up routine)
        self.controller.arm.add_cycle_listener(self.egm.on_cycle)
        self._started = False

    def _egm_state(self) -> tuple[bool, bool]:
        c = self.controller
        return c.ctrlstate == "motoron", c.execution.state == "running"

    # ----------------------------------------------------------------------------- lifecycle
    def start(self) -> dict[str, Any]:
        """Listen for RWS and start the controller (and its EGM stream); returns the endpoints."""
        self.rws.start()
        self.controller.start()
        self._started = True
        return self.endpoints()

    def stop(self) -> None:
        if not self._started:
            self.egm.close()
            self.rws.httpd.server_close()
            return
        self._started = False
        self.controller.stop()
        self.rws.stop()
        self.egm.close()

    def endpoints(self) -> dict[str, Any]:
        return {"host": self.host, "rws_port": self.rws.port, "base_url": f"http://{self.host}:{self.rws.port}",
                "egm_remote": list(self.egm.remote), "robot_type": self.config.robot_type,
                "rw_version": self.config.rw_version_name, "time_scale": self.config.time_scale}

    # ----------------------------------------------------------------------------- control API
    def state(self) -> dict[str, Any]:
        """The controller's state now: panel, RAPID, the arm's joints and poses."""
        return self.controller.describe()

    def visits(self, since: int = 0) -> list[dict[str, Any]]:
        """True attained poses of the finished moves, from index ``since`` on."""
        with self.controller.arm.lock:
            return list(self.controller.arm.visits[int(since):])

    def truth(self, event: str | None = "pose") -> list[dict[str, Any]]:
        return self.world.truth.entries(event)

    def events(self) -> list[str]:
        with self.controller.arm.lock:
            return list(self.controller.arm.events)

    def elog(self, count: int = 50) -> list[dict[str, Any]]:
        """The newest ``count`` event log entries."""
        with self.controller.lock:
            return [vars(entry).copy() for entry in self.controller.elog[:int(count)]]

    def arm_fault(self, kind: str, count: int = 1, **params: Any) -> list[str]:
        """Arm a fault (a ``FaultKind`` or ``motors_off``); robot faults fire mid-move at path fraction
        ``at`` (default 0.5). Returns what is armed."""
        if kind in LOCAL_FAULTS:
            for _ in range(max(int(count), 1)):
                self.controller.arm.local_faults.append((kind, dict(params)))
        else:
            self.faults.arm(fault_kind(kind), int(count), **params)
        return [a.kind.value for a in self.faults.armed()] + [name for name, _ in self.controller.arm.local_faults]

    def trigger(self, kind: str, **params: Any) -> dict[str, Any]:
        """Make ``protective_stop`` (guard stop), ``emergency_stop``, ``motors_off``, ``program_stopped``
        (a RAPID error: ``code``, ``title``, ``text``) or ``disconnect`` happen now."""
        if kind == FaultKind.PROGRAM_STOPPED.value:
            self.controller._inject_rapid_error(int(params.get("code", 40223)),
                                                str(params.get("title", "Execution error")),
                                                str(params.get("text", "Execution error (injected)")), None)
        else:
            self.controller._fault(kind if kind in LOCAL_FAULTS else fault_kind(kind))
        return self.state()

    def clear_faults(self) -> dict[str, Any]:
        """Disarm every fault, end an EGM stall, reset safety stops and switch the motors on."""
        self.egm.stall_until = -1.0
        self.egm.drop = 0
        self.controller.clear_faults()
        return self.state()

    def release_safety(self) -> dict[str, Any]:
        """Reset a guard or emergency stop; the controller waits in motors off."""
        self.controller.release_safety()
        return self.state()

    def fired(self) -> list[tuple[str, dict[str, Any]]]:
        local = [(name, params) for name, params in self.controller.arm.fired_local]
        return [(k.value, p) for k, p in self.faults.fired()] + local

    def set_repeatability(self, translation_std: float | None = None, rotation_std: float | None = None,
                          approach_bias: float | None = None, drift_amplitude: float | None = None,
                          drift_time_constant: float | None = None) -> dict[str, Any]:
        """Change the attained-pose error model from now on (SI units); returns the whole config."""
        changes = {"repeatability_translation_std": translation_std, "repeatability_rotation_std": rotation_std,
                   "approach_bias": approach_bias, "thermal_drift_amplitude": drift_amplitude,
                   "thermal_drift_time_constant": drift_time_constant}
        for field_name, value in changes.items():
            if value is not None:
                setattr(self.config, field_name, float(value))
        return self.config.to_dict()

    def egm_stats(self) -> dict[str, Any]:
        """Packets sent and lost, the last sequence number, the remote address."""
        return self.egm.stats()

    def connections(self) -> dict[str, Any]:
        rws = self.rws
        with rws._lock:
            return {"sessions": len(rws.sessions), "requests": rws.requests,
                    "subscriptions": {n: len(g.sockets) for n, g in rws.subscriptions.items()}}

    def files(self) -> dict[str, int]:
        """The RAMDISK's files and their sizes."""
        with self.controller.lock:
            return {name: len(data) for name, data in self.controller.files.items()}

    def describe(self) -> dict[str, Any]:
        return {"config": self.config.to_dict(), "world": self.world.describe(), "endpoints": self.endpoints()}

    def control(self, command: str, /, **kwargs: Any) -> Any:
        """The twin's control API (also through ``TwinProcess.call``): ``endpoints``, ``state``, ``visits``
        (since), ``truth`` (event), ``events``, ``elog`` (count), ``arm_fault`` (kind, count, params),
        ``trigger`` (kind, params), ``clear_faults``, ``release_safety``, ``fired``, ``set_repeatability``,
        ``egm_stats``, ``connections``, ``files``, ``describe``."""
        commands: dict[str, Callable[..., Any]] = {
            "endpoints": self.endpoints, "state": self.state, "visits": self.visits, "truth": self.truth,
            "events": self.events, "elog": self.elog, "arm_fault": self.arm_fault, "trigger": self.trigger,
            "clear_faults": self.clear_faults, "release_safety": self.release_safety, "fired": self.fired,
            "set_repeatability": self.set_repeatability, "egm_stats": self.egm_stats,
            "connections": self.connections, "files": self.files, "describe": self.describe,
        }
        return dispatch(commands, command, kwargs, "ABB twin")


def standalone_host(host: str = "127.0.0.2", port: int = RWS_PORT, seed: int = 0, time_scale: float = 1.0,
                    world: Mapping[str, Any] | None = None, truth_path: str | None = None,
                    **config: Any) -> ABBControllerTwin:
    """Factory for ``TwinProcess``: a twin with its own ``World`` (seeded with ``seed``; the flange
    starts at ``IRB2600_REFERENCE_FLANGE`` unless ``world`` says otherwise). Extra keyword arguments
    go to ``ABBTwinConfig``."""
    world_data = {"seed": seed, **dict(world or {})}
    kinematics = dict(world_data.get("kinematics") or {})
    kinematics.setdefault("reference_flange_pose", IRB2600_REFERENCE_FLANGE)
    world_data["kinematics"] = kinematics
    twin_config = ABBTwinConfig.from_dict({"seed": seed, "time_scale": time_scale, **config})
    return ABBControllerTwin(World(WorldConfig.from_dict(world_data), truth_path=truth_path), host, twin_config,
                             port=port)
