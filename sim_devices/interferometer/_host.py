"""Host objects: ``InterferometerTwin`` (embedded in a cell sharing its ``World``) and
``StandaloneInterferometerHost`` (its own world, for ``TwinProcess``)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from sim_devices.control import dispatch
from sim_devices.faults import FaultKind, FaultPlan
from sim_devices.interferometer._config import FeedLayout, InterferometerTwinConfig
from sim_devices.interferometer._device import InterferometerDevice
from sim_devices.interferometer._environment import EnvironmentUnit
from sim_devices.interferometer._head import InterferometerHead
from sim_devices.interferometer._slcan import SlcanPort
from sim_devices.interferometer._socketcand import SocketcandServer
from sim_devices.world import World, WorldConfig


class InterferometerTwin:
    """The laser interferometer twin: head physics on ``world``, a 1 kHz CAN feed served by a
    socketcand daemon (TCP on loopback) and an slcan adapter (pty), fault injection.

    Parameters
    ----------
    world : World
        The shared truth; the head measures the OPR origin's motion along its beam.
    config : mapping or InterferometerTwinConfig, optional
        See ``InterferometerTwinConfig``.

    ``start()`` returns the endpoints::

        {"socketcand": {"host", "port", "channel"}, "slcan": {"port"}, "layout": {...}}

    ``control(command, **kw)``: ``align`` (axis), ``arm`` (kind, count=1, **params), ``clear``
    (kinds=[] → all), ``truth``, ``stats``, ``fired``, ``endpoints``, ``station_entry``
    (transport="socketcand"), ``environment`` (the true air and the environmental unit's state),
    ``sensor_fault`` (sensor, faulty=True). ``faults`` is the twin's ``FaultPlan`` for in-process use.
    """

    def __init__(self, world: World, config: Mapping[str, Any] | InterferometerTwinConfig | None = None) -> None:
        self.world = world
        self.config = InterferometerTwinConfig.from_dict(config)
        self.faults = FaultPlan()
        self.head: InterferometerHead | None = None
        self.environment_unit: EnvironmentUnit | None = None
        self.device: InterferometerDevice | None = None
        self._socketcand: SocketcandServer | None = None
        self._slcan: SlcanPort | None = None
        self.endpoints: dict[str, Any] = {}

    # ------------------------------------------------------------------------------ lifecycle
    def start(self) -> dict[str, Any]:
        config = self.config
        try:
            self.head = InterferometerHead(self.world, config)
            self.environment_unit = EnvironmentUnit(self.world, config)
            self.head.refraction_ratio = self.environment_unit.refraction_ratio(self.environment_unit.conditions())
            # The air is a function of time alone: its origin and the sensors' offsets make it recomputable.
            self.world.truth.record("interferometer_environment", time=self.world.clock(),
                                    **self.environment_unit.truth())
            self.device = InterferometerDevice(self.head, self.environment_unit, config, self.faults,
                                               self.world.noise_rng("interferometer junk"),
                                               self.world.noise_rng("interferometer bus timing"))
            self.endpoints = {"layout": config.layout.to_dict()}
            if config.socketcand:
                self._socketcand = SocketcandServer(config.host, config.port, config.channel, self.device.on_command,
                                                    config.first_frame_pause)
                self.endpoints["socketcand"] = self._socketcand.start()
                self.device.transports["socketcand"] = self._socketcand
            if config.slcan:
                self._slcan = SlcanPort(self.device.on_command)
                self.endpoints["slcan"] = self._slcan.start()
                self.device.transports["slcan"] = self._slcan
            self.device.start()
        except BaseException:
            self.stop()
            raise
        return self.endpoints

    def stop(self) -> None:
        if self.device is not None:
            self.device.stop()
        for transport in (self._socketcand, self._slcan):
            if transport is not None:
                transport.stop()
        self._socketcand = self._slcan = None
        if self.head is not None:
            self.head.close()
        self.device = self.head = self.environment_unit = None

    def __enter__(self) -> InterferometerTwin:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------------------ control API
    def align(self, axis: str) -> dict[str, Any]:
        """The operator re-aims the head along M's ``axis`` (the count is lost: zero() again)."""
        head, _ = self._running()
        truth = head.align(axis)
        self.world.truth.record("interferometer_align", time=self.world.clock(), **truth)
        return truth

    def truth(self) -> dict[str, Any]:
        """The head's truth (beam, scale error, refraction ratio, datum, true displacement)."""
        head, _ = self._running()
        return head.truth()

    def environment(self) -> dict[str, Any]:
        """The true air now (``air``: °C, Pa, % RH, ppm, material °C), both refractive indices and
        their ratio, the ambient model's time ``origin`` on the world clock, the fitted sensors, their
        calibration offsets (°C, Pa, % RH) and the sensors reporting a fault."""
        return self._environment_unit().truth()

    def sensor_fault(self, sensor: str, faulty: bool = True) -> list[str]:
        """Make an environmental sensor (``air_temperature``, ``pressure``, ``humidity``,
        ``material1``..``material3`` if fitted) report a fault, or stop; returns those that do."""
        return self._environment_unit().set_fault(sensor, bool(faulty))

    def arm(self, kind: FaultKind | str, count: int = 1, **params: Any) -> list[str]:
        """Arm a feed fault (see ``_device.py`` for the kinds and their params); returns what is armed."""
        self.faults.arm(FaultKind(kind), int(count), **params)
        return [a.kind.value for a in self.faults.armed()]

    def clear(self, kinds: tuple[FaultKind | str, ...] | list[FaultKind | str] = ()) -> list[str]:
        """Disarm ``kinds`` (all when empty); returns what is still armed."""
        self.faults.clear(*kinds)
        return [a.kind.value for a in self.faults.armed()]

    def fired(self) -> list[list[Any]]:
        """Every fault fired so far, oldest first, as ``[kind, params]``."""
        return [[kind.value, params] for kind, params in self.faults.fired()]

    def stats(self) -> dict[str, int]:
        """Frame counters of the head's clock and its transports."""
        _, device = self._running()
        stats = device.snapshot()
        stats["slcan_overflows"] = self._slcan.overflows if self._slcan else 0
        stats["socketcand_connections"] = self._socketcand.connections if self._socketcand else 0
        return stats

    def station_entry(self, transport: str = "socketcand") -> dict[str, Any]:
        """The ``devices.interferometer`` entry of a station file for this twin (with the head's
        ``optics``: its vacuum wavelength and the nominal air it computes with, in SI)."""
        if transport == "socketcand" and "socketcand" in self.endpoints:
            entry = {"adapter": "socketcand", **self.endpoints["socketcand"]}
        elif transport == "slcan" and "slcan" in self.endpoints:
            entry = {"adapter": "slcan", "port": self.endpoints["slcan"]["port"]}
        else:
            raise ValueError(f"interferometer twin: transport {transport!r} is not running")
        config = self.config
        entry["optics"] = {"vacuum_wavelength": config.vacuum_wavelength,
                           "nominal_air_temperature": config.nominal_air_temperature_c + 273.15,
                           "nominal_pressure": config.nominal_pressure_pa,
                           "nominal_relative_humidity": config.nominal_relative_humidity_percent / 100.0,
                           "nominal_co2": config.nominal_co2_ppm}
        if config.layout != FeedLayout():
            entry["layout"] = config.layout.to_dict()
        return entry

    def control(self, command: str, /, **kwargs: Any) -> Any:
        """The host API for ``TwinProcess``: each command is the method of that name (``endpoints``:
        the attribute)."""
        commands: dict[str, Callable[..., Any]] = {
            "align": self.align, "arm": self.arm, "clear": self.clear, "fired": self.fired, "truth": self.truth,
            "stats": self.stats, "endpoints": lambda: self.endpoints, "station_entry": self.station_entry,
            "environment": self.environment, "sensor_fault": self.sensor_fault,
        }
        return dispatch(commands, command, kwargs, "interferometer twin")

    def _environment_unit(self) -> EnvironmentUnit:
        if self.environment_unit is None:
            raise RuntimeError("interferometer twin is not running (call start())")
        return self.environment_unit

    def _running(self) -> tuple[InterferometerHead, InterferometerDevice]:
        if self.head is None or self.device is None:
            raise RuntimeError("interferometer twin is not running (call start())")
        return self.head, self.device


class StandaloneInterferometerHost:
    """An ``InterferometerTwin`` with a world of its own, for ``TwinProcess``
    (``"sim_devices.interferometer:StandaloneInterferometerHost"``).

    Adds control commands to move the world: ``set_flange_pose`` (pose: 6 values or 4×4),
    ``move_opr`` (delta: 3 values, metres in M: translates the OPR without rotating it),
    ``opr_in_m`` (4×4 as nested lists).
    """

    def __init__(self, seed: int = 0, config: Mapping[str, Any] | None = None) -> None:
        self.world = World(WorldConfig(seed=int(seed)))
        self.twin = InterferometerTwin(self.world, config)

    def start(self) -> dict[str, Any]:
        return self.twin.start()

    def stop(self) -> None:
        self.twin.stop()
        self.world.truth.close()

    def set_flange_pose(self, pose: list[float] | list[list[float]]) -> list[list[float]]:
        """Put the flange at ``pose`` (a UR pose of 6 values, or 4×4, in B); returns the OPR in M."""
        self.world.set_flange_pose(np.asarray(pose, dtype=float))
        return self.opr_in_m()

    def move_opr(self, delta: list[float]) -> list[list[float]]:
        """Translate the OPR by ``delta`` (metres, in M); returns the OPR in M."""
        move_opr(self.world, delta)
        return self.opr_in_m()

    def opr_in_m(self) -> list[list[float]]:
        return self.world.opr_in_m().tolist()

    def control(self, command: str, /, **kwargs: Any) -> Any:
        """The world commands above, then every command of ``InterferometerTwin.control``."""
        commands: dict[str, Callable[..., Any]] = {"set_flange_pose": self.set_flange_pose,
                                                   "move_opr": self.move_opr, "opr_in_m": self.opr_in_m}
        if command in commands:
            return dispatch(commands, command, kwargs, "interferometer host")
        return self.twin.control(command, **kwargs)


def move_opr(world: World, delta_in_m) -> None:
    """Translate the OPR by ``delta_in_m`` (metres, in M) by moving the flange (OPR on the robot)."""
    shift = np.eye(4)
    shift[:3, 3] = np.asarray(delta_in_m, dtype=float)
    # T_B_F' = T_B_M · shift · T_M_B · T_B_F moves the OPR by ``shift`` expressed in M.
    base_to_m = world.base_to_m
    world.set_flange_pose(base_to_m @ shift @ np.linalg.inv(base_to_m) @ world.flange_pose(), source="test")
