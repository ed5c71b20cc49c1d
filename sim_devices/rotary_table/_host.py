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
from dataclasses import dataclass, field
from typing import Any, Literal, cast

from sim_devices._config import checked_fields
from sim_devices.control import dispatch
from sim_devices.faults import FaultKind, FaultPlan
from sim_devices.rotary_table._gcs import GcsTableTwin
from sim_devices.rotary_table._gcs_tcp import GcsTcpTwin
from sim_devices.rotary_table._modbus import ModbusTableTwin
from sim_devices.rotary_table._physics import TableConfig, TablePhysics
from sim_devices.rotary_table._register_map import DriveRegisterMap
from sim_devices.world import Axis, World, WorldConfig

Transport = Literal["modbus_tcp", "modbus_rtu", "gcs", "gcs_tcp"]
TRANSPORTS: tuple[Transport, ...] = ("modbus_tcp", "modbus_rtu", "gcs", "gcs_tcp")


@dataclass(frozen=True)
class RotaryTableTwinConfig:
    """The ``rotary_table`` section of a cell configuration (see ``RotaryTableTwin``)."""

    transports: tuple[Transport, ...] = TRANSPORTS
    table: Mapping[str, Any] = field(default_factory=dict)
    register_map: DriveRegisterMap = field(default_factory=DriveRegisterMap)
    unit: int = 1
    tcp_port: int = 0
    gcs_tcp_port: int = 0
    seed: int | None = None
    tick: float = 0.01
    world_rate: float = 50.0

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> RotaryTableTwinConfig:
        settings = checked_fields(cls, data, "rotary table twin")
        if "transports" in settings:
            transports = tuple(settings["transports"])
            bad = set(transports) - set(TRANSPORTS)
            if bad:
                raise ValueError(f"rotary table twin: unknown transport(s) {sorted(bad)}; known: {list(TRANSPORTS)}")
            settings["transports"] = cast(tuple[Transport, ...], transports)
        settings["register_map"] = DriveRegisterMap.from_config(settings.get("register_map"))
        settings["table"] = dict(settings.get("table") or {})
        for key, kind in (("unit", int), ("tcp_port", int), ("gcs_tcp_port", int), ("tick", float),
                          ("world_rate", float)):
            if key in settings:
                settings[key] = kind(settings[key])
        if settings.get("seed") is not None:
            settings["seed"] = int(settings["seed"])
        config = cls(**settings)
        if not 1 <= config.unit <= 247:
            raise ValueError(f"rotary table twin: unit must be a Modbus device id 1..247 (0 is broadcast), "
                             f"got {config.unit}")
        if not (config.tick > 0 and config.world_rate > 0):
            raise ValueError("rotary table twin: tick and world_rate must be > 0")
        return config


class RotaryTableTwin:
    """Host object (``start``/``stop``/``control``) of the simulated rotary table.

    Parameters
    ----------
    world : World
        The shared truth; the table's TRUE angle is written with ``world.set_table_angle`` while the
        OPR is mounted on the table (``world.mount == "table:<axis>"``). It is not written while the
        OPR is on the robot, because the world's single ``settled`` flag then belongs to the robot.
    config : mapping
        ``transports`` (subset of ``modbus_tcp``, ``modbus_rtu``, ``gcs`` (serial), ``gcs_tcp``;
        default all), ``table`` (``TableConfig`` fields), ``register_map`` (``RegisterMap`` fields),
        ``unit`` (Modbus id, 1), ``tcp_port`` (Modbus TCP, 0 = OS-chosen), ``gcs_tcp_port`` (GCS on
        TCP, 0 = OS-chosen; a real PI controller uses 50000), ``seed`` (defaults to the world's),
        ``tick`` (s between physics updates in the background, 0.01), ``world_rate`` (Hz of unsettled
        angle updates, 50). The table powers on with the servo off and unreferenced.
    clock : callable
        Monotonic seconds for the physics (inject a fake clock in tests).
    """

    def __init__(self, world: World, config: Mapping[str, Any] | RotaryTableTwinConfig | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        settings = config if isinstance(config, RotaryTableTwinConfig) else RotaryTableTwinConfig.from_dict(config)
        self.config = settings
        self.world = world
        self.transports = settings.transports
        seed = world.config.seed if settings.seed is None else settings.seed
        self.table_config = TableConfig.from_dict({"seed": seed, **settings.table})
        self.register_map = settings.register_map
        self.tick = settings.tick
        self._min_interval = 1.0 / settings.world_rate
        self._last_unsettled = -1e9
        # The state for the world waits here for the publisher thread: the physics tells it under its
        # lock, and a settled state's publication waits for every camera to render it, which must
        # never hold up the drive's answers (a status read would time out in the driver).
        self._mail = threading.Condition()
        self._pending: tuple[float, bool] | None = None
        self._publishing = False
        self.physics = TablePhysics(self.table_config, clock=clock, on_change=self._to_world,
                                    initial_angle=world.table_angle(), seen=self._seen)
        self.modbus: ModbusTableTwin | None = None
        self.gcs: GcsTableTwin | None = None
        if {"modbus_tcp", "modbus_rtu"} & set(self.transports):
            self.modbus = ModbusTableTwin(self.physics, self.register_map, unit=settings.unit,
                                          tcp="modbus_tcp" in self.transports, rtu="modbus_rtu" in self.transports,
                                          tcp_port=settings.tcp_port, seed=seed)
        if "gcs" in self.transports:
            self.gcs = GcsTableTwin(self.physics, seed=seed)
        self.gcs_tcp: GcsTcpTwin | None = None
        if "gcs_tcp" in self.transports:
            self.gcs_tcp = GcsTcpTwin(self.physics, port=settings.gcs_tcp_port)
        self._stop = threading.Event()
        self._ticker: threading.Thread | None = None
        self._publisher: threading.Thread | None = None
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
        if self._publisher is None:  # not started (a test's fake clock): the world at once
            self.world.set_table_angle(angle, settled=settled)
            return
        with self._mail:
            self._pending = (angle, settled)  # the latest wins: the world needs no stale in-between angle
            self._mail.notify_all()

    def _seen(self) -> bool:
        """Everything the physics told has reached the world (a settled angle: every camera has it)."""
        with self._mail:
            return self._pending is None and not self._publishing

    def _publish_to_world(self) -> None:
        while True:
            with self._mail:
                while self._pending is None and not self._stop.is_set():
                    self._mail.wait(0.5)
                if self._pending is None:
                    return
                angle, settled = self._pending
                self._pending, self._publishing = None, True
            try:
                self.world.set_table_angle(angle, settled=settled)
            finally:
                with self._mail:
                    self._publishing = False
                    self._mail.notify_all()

    def _tick(self) -> None:
        while not self._stop.wait(self.tick):
            self.sync(wait=False)

    def sync(self, wait: bool = True, timeout: float = 30.0) -> None:
        """Advance the physics now and bring the world up to date (e.g. right after a re-mount); with
        ``wait``, return once the world has it (at most ``timeout`` s)."""
        if self.world.mount.startswith("table") and self.world.table_angle() != self.physics.true_angle():
            self.physics.forget_published()
        self.physics.update()
        if wait and self._publisher is not None:
            with self._mail:
                self._mail.wait_for(self._seen, timeout)  # _seen takes the same (reentrant) lock

    # ----------------------------------------------------------------------------- host API
    def faults(self, transport: str) -> FaultPlan:
        """The fault plan of one endpoint: ``modbus_tcp``, ``modbus_rtu``, ``gcs`` or ``gcs_tcp``."""
        if transport == "modbus_tcp" and self.modbus is not None:
            return self.modbus.faults
        if transport == "modbus_rtu" and self.modbus is not None:
            return self.modbus.rtu_faults
        if transport == "gcs" and self.gcs is not None:
            return self.gcs.faults
        if transport == "gcs_tcp" and self.gcs_tcp is not None:
            return self.gcs_tcp.faults
        raise ValueError(f"rotary table twin: no transport {transport!r} running (have {list(self.transports)})")

    def start(self) -> dict[str, Any]:
        try:
            if self.modbus is not None:
                self.endpoints.update(self.modbus.start())
            if self.gcs is not None:
                self.endpoints.update(self.gcs.start())
            if self.gcs_tcp is not None:
                self.endpoints.update(self.gcs_tcp.start())
        except BaseException:
            self.stop()
            raise
        self._stop.clear()
        self._publisher = threading.Thread(target=self._publish_to_world, name="rotary table to world", daemon=True)
        self._publisher.start()
        self._ticker = threading.Thread(target=self._tick, name="rotary table ticker", daemon=True)
        self._ticker.start()
        return dict(self.endpoints)

    def stop(self) -> None:
        self._stop.set()
        with self._mail:
            self._mail.notify_all()
        if self._ticker is not None:
            self._ticker.join(5.0)
            self._ticker = None
        if self._publisher is not None:
            self._publisher.join(15.0)
            self._publisher = None
        for face in (self.modbus, self.gcs, self.gcs_tcp):
            if face is not None:
                face.stop()

    def truth(self) -> dict[str, Any]:
        """True angle, settled flag, reported counts, error bound and the drive status now."""
        status = self.physics.status()
        return {
            "true_angle": self.physics.true_angle(),
            "settled": self.physics.settled(),
            "reported_counts": self.physics.read_counts(),
            "counts_per_rev": self.table_config.counts_per_rev,
            "error_bound": self.table_config.reported_error_bound(),
            **dict(status.items()),
        }

    # ----------------------------------------------------------------------------- typed control
    def arm(self, transport: str, kind: FaultKind | str, count: int = 1, **params: Any) -> None:
        """Arm a fault on one endpoint (``modbus_tcp``, ``modbus_rtu``, ``gcs`` or ``gcs_tcp``)."""
        self.faults(transport).arm(kind, int(count), **params)

    def clear(self, transport: str, kinds: tuple[FaultKind | str, ...] | list[FaultKind | str] = ()) -> None:
        """Disarm ``kinds`` (all when empty) on one endpoint."""
        self.faults(transport).clear(*kinds)

    def fired(self, transport: str) -> list[tuple[str, dict[str, Any]]]:
        """Every fault fired on one endpoint so far, oldest first."""
        return [(kind.value, params) for kind, params in self.faults(transport).fired()]

    def raise_alarm(self, name: str = "following_error") -> None:
        """A drive alarm: the table stops and refuses moves until ``alarm_reset``."""
        self.physics.raise_alarm(name)

    def alarm_reset(self) -> None:
        self.physics.alarm_reset()

    def describe(self) -> dict[str, Any]:
        return {"table": self.table_config.to_dict(), "register_map": self.register_map.to_config(),
                "transports": list(self.transports)}

    def control(self, command: str, /, **kwargs: Any) -> Any:
        """The host API for ``TwinProcess``: ``arm`` (transport, kind, count=1, **params), ``clear``
        (transport, kinds), ``fired`` (transport), ``truth``, ``alarm`` (name), ``alarm_reset``,
        ``endpoints``, ``describe``; each is the method of that name (``alarm``: ``raise_alarm``)."""
        commands: dict[str, Callable[..., Any]] = {
            "arm": self.arm, "clear": self.clear, "fired": self.fired, "truth": self.truth,
            "alarm": self.raise_alarm, "alarm_reset": self.alarm_reset, "endpoints": lambda: dict(self.endpoints),
            "describe": self.describe,
        }
        return dispatch(commands, command, kwargs, "rotary table twin")


def make_host(config: Mapping[str, Any] | None = None, world: Mapping[str, Any] | None = None,
              mount: str | None = None) -> RotaryTableTwin:
    """Factory for ``TwinProcess("sim_devices.rotary_table:make_host", {...})``: a twin with its own world.

    ``mount`` (``"x"``, ``"y"`` or ``"z"``) puts the OPR on the table so the world follows the angle.
    """
    own_world = World(WorldConfig.from_dict(world))
    if mount:
        own_world.mount_on_table(cast(Axis, mount))
    return RotaryTableTwin(own_world, config)
