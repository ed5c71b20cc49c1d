"""``RotaryTableTwin``: the table physics, its protocol faces, and its link to the ``World``.

The cell embeds it in-process (so the true table angle lands in the same ``World`` as the cameras)::

    twin = RotaryTableTwin(world, {"transports": ["modbus_tcp"], "seed": 3})
    endpoints = twin.start()   # {"modbus_tcp_port": 40123, ...}
    twin.faults("modbus_tcp").arm("exception", code=4)
    twin.stop()

``make_host(config, world=None)`` builds one with a private world for ``TwinProcess``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from drivers.rotary_table._registers import RegisterMap
from sim_devices.faults import FaultPlan
from sim_devices.rotary_table._gcs import GcsTableTwin
from sim_devices.rotary_table._modbus import ModbusTableTwin
from sim_devices.rotary_table._physics import TableConfig, TablePhysics
from sim_devices.world import World, WorldConfig

TRANSPORTS = ("modbus_tcp", "modbus_rtu", "gcs")
_CONFIG_KEYS = {"transports", "table", "register_map", "unit", "tcp_port", "seed", "tick", "world_rate"}


class RotaryTableTwin:
    """Host object (``start``/``stop``/``control``) of the simulated rotary table.

    Parameters
    ----------
    world : World
        The shared truth; the table's TRUE angle is written with ``world.set_table_angle`` while the
        OPR is mounted on the table (``world.mount == "table:<axis>"``). It is not written while the
        OPR is on the robot, because the world's single ``settled`` flag then belongs to the robot.
    config : mapping
        ``transports`` (subset of ``modbus_tcp``, ``modbus_rtu``, ``gcs``; default all), ``table``
        (``TableConfig`` fields), ``register_map`` (``RegisterMap`` fields), ``unit`` (Modbus id, 1),
        ``tcp_port`` (0 = OS-chosen), ``seed`` (defaults to the world's), ``tick`` (s between physics
        updates in the background, 0.01), ``world_rate`` (Hz of unsettled angle updates, 50).
    clock : callable
        Monotonic seconds for the physics (inject a fake clock in tests).
    """

    def __init__(self, world: World, config: Mapping[str, Any] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        config = dict(config or {})
        unknown = set(config) - _CONFIG_KEYS
        if unknown:
            raise ValueError(
                f"rotary table twin: unknown config key(s) {sorted(unknown)}; known: {sorted(_CONFIG_KEYS)}"
            )
        self.world = world
        self.transports = tuple(config.get("transports", TRANSPORTS))
        bad = set(self.transports) - set(TRANSPORTS)
        if bad:
            raise ValueError(f"rotary table twin: unknown transport(s) {sorted(bad)}; known: {list(TRANSPORTS)}")
        seed = int(config.get("seed", world.config.seed))
        table = dict(config.get("table") or {})
        table.setdefault("seed", seed)
        self.table_config = TableConfig.from_dict(table)
        self.register_map = RegisterMap.from_config(config.get("register_map"))
        self.tick = float(config.get("tick", 0.01))
        self._min_interval = 1.0 / float(config.get("world_rate", 50.0))
        self._last_unsettled = -1e9
        self._published: tuple[float, bool] | None = None
        self.physics = TablePhysics(self.table_config, clock=clock, on_change=self._to_world,
                                    initial_angle=world.table_angle())
        self.modbus: ModbusTableTwin | None = None
        self.gcs: GcsTableTwin | None = None
        if {"modbus_tcp", "modbus_rtu"} & set(self.transports):
            self.modbus = ModbusTableTwin(self.physics, self.register_map, unit=int(config.get("unit", 1)),
                                          tcp="modbus_tcp" in self.transports, rtu="modbus_rtu" in self.transports,
                                          tcp_port=int(config.get("tcp_port", 0)), seed=seed)
        if "gcs" in self.transports:
            self.gcs = GcsTableTwin(self.physics, seed=seed)
        self._stop = threading.Event()
        self._ticker: threading.Thread | None = None
        self.endpoints: dict[str, Any] = {}

    # ----------------------------------------------------------------------------- world link
    def _to_world(self, angle: float, settled: bool) -> None:
        if not self.world.mount.startswith("table"):
            return
        now = time.monotonic()
        if not settled and now - self._last_unsettled < self._min_interval:
            return
        if not settled:
            self._last_unsettled = now
        self._published = (angle, settled)
        self.world.set_table_angle(angle, settled=settled)

    def _tick(self) -> None:
        while not self._stop.wait(self.tick):
            self.sync()

    def sync(self) -> None:
        """Advance the physics now and bring the world up to date (e.g. right after a re-mount)."""
        if self.world.mount.startswith("table") and self.world.table_angle() != self.physics.true_angle():
            self.physics.forget_published()
        self.physics.update()

    # ----------------------------------------------------------------------------- host API
    def faults(self, transport: str) -> FaultPlan:
        """The fault plan of one endpoint: ``modbus_tcp``, ``modbus_rtu`` or ``gcs``."""
        if transport == "modbus_tcp" and self.modbus is not None:
            return self.modbus.faults
        if transport == "modbus_rtu" and self.modbus is not None:
            return self.modbus.rtu_faults
        if transport == "gcs" and self.gcs is not None:
            return self.gcs.faults
        raise ValueError(f"rotary table twin: no transport {transport!r} running (have {list(self.transports)})")

    def start(self) -> dict[str, Any]:
        try:
            if self.modbus is not None:
                self.endpoints.update(self.modbus.start())
            if self.gcs is not None:
                self.endpoints.update(self.gcs.start())
        except BaseException:
            self.stop()
            raise
        self._stop.clear()
        self._ticker = threading.Thread(target=self._tick, name="rotary table ticker", daemon=True)
        self._ticker.start()
        return dict(self.endpoints)

    def stop(self) -> None:
        self._stop.set()
        if self._ticker is not None:
            self._ticker.join(5.0)
            self._ticker = None
        for face in (self.modbus, self.gcs):
            if face is not None:
                face.stop()

    def truth(self) -> dict[str, Any]:
        status = self.physics.status()
        return {
            "true_angle": self.physics.true_angle(),
            "settled": self.physics.settled(),
            "reported_counts": self.physics.read_counts(),
            "counts_per_rev": self.table_config.counts_per_rev,
            "error_bound": self.table_config.reported_error_bound(),
            **dict(status.items()),
        }

    def control(self, command: str, **kwargs: Any) -> Any:
        """``arm`` (transport, kind, count=1, **params), ``clear`` (transport, kinds), ``fired``
        (transport), ``truth``, ``alarm`` (name), ``alarm_reset``, ``endpoints``, ``describe``."""
        if command == "arm":
            transport, kind = kwargs.pop("transport"), kwargs.pop("kind")
            self.faults(transport).arm(kind, int(kwargs.pop("count", 1)), **kwargs)
            return None
        if command == "clear":
            self.faults(kwargs["transport"]).clear(*kwargs.get("kinds", ()))
            return None
        if command == "fired":
            return [(kind.value, params) for kind, params in self.faults(kwargs["transport"]).fired()]
        if command == "truth":
            return self.truth()
        if command == "alarm":
            self.physics.raise_alarm(kwargs.get("name", "following_error"))
            return None
        if command == "alarm_reset":
            self.physics.alarm_reset()
            return None
        if command == "endpoints":
            return dict(self.endpoints)
        if command == "describe":
            return {"table": self.table_config.to_dict(), "register_map": self.register_map.to_config(),
                    "transports": list(self.transports)}
        raise ValueError(f"rotary table twin: unknown control command {command!r}")


def make_host(config: Mapping[str, Any] | None = None, world: Mapping[str, Any] | None = None,
              mount: str | None = None) -> RotaryTableTwin:
    """Factory for ``TwinProcess("sim_devices.rotary_table:make_host", {...})``: a twin with its own world.

    ``mount`` (``"x"``, ``"y"`` or ``"z"``) puts the OPR on the table so the world follows the angle.
    """
    own_world = World(WorldConfig.from_dict(world))
    if mount:
        own_world.mount_on_table(mount)  # type: ignore[arg-type]
    return RotaryTableTwin(own_world, config)
