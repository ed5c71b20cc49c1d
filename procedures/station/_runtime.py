"""A station at run time: its devices (made by the driver factories), envelope and operator."""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping
from typing import Any, Protocol, TypeVar

import numpy as np

import drivers.camera
import drivers.interferometer
import drivers.robot
import drivers.rotary_table
from drivers import DeviceConnectionError, DeviceError
from drivers.camera import Camera
from drivers.interferometer import Interferometer
from drivers.robot import MotionEnvelope, Robot
from drivers.rotary_table import RotaryTable
from instrument import SCREENS
from procedures.station._models import StationFile


class Operator(Protocol):
    """Who changes the set-up between axes: a person at the console, or the simulated cell."""

    def mount_opr(self, where: str) -> None:
        """``where`` is ``"robot"`` or ``"table:x"`` / ``"table:y"`` / ``"table:z"``."""
        ...

    def align_interferometer(self, axis: str) -> None: ...


class ConsoleOperator:
    """Asks the person at the terminal and waits for Enter."""

    def __init__(self, prompt: Callable[[str], str] = input, stream=sys.stderr) -> None:
        self._prompt, self._stream = prompt, stream

    def _ask(self, text: str) -> None:
        print(f"\n>>> OPERATOR: {text}", file=self._stream)
        self._prompt(">>> press Enter when done (Ctrl-C pauses the run) ")

    def mount_opr(self, where: str) -> None:
        if where == "robot":
            self._ask("mount the optical pose reference back on the robot flange")
        else:
            self._ask(f"mount the optical pose reference on the rotary table for axis {where.split(':')[1]} "
                      "(table axis along M's axis, through M's origin)")

    def align_interferometer(self, axis: str) -> None:
        self._ask(f"align the laser interferometer to M's {axis} axis (beam along the OPR's motion)")


class SimulationOperator:
    """The simulated cell's control channel plays the operator.

    Commands sent: ``mount_on_robot``, ``mount_on_table(axis=...)``,
    ``align_interferometer(axis=...)`` (the cell's control API).
    """

    def __init__(self, host: str, port: int, timeout: float = 30.0) -> None:
        from sim_devices.control import ControlClient  # only for simulated stations

        self.client = ControlClient(host, port, timeout=timeout)

    def mount_opr(self, where: str) -> None:
        if where == "robot":
            self.client.call("mount_on_robot")
        else:
            self.client.call("mount_on_table", axis=where.split(":")[1])

    def align_interferometer(self, axis: str) -> None:
        self.client.call("align_interferometer", axis=axis)


class NoOperator:
    def mount_opr(self, where: str) -> None:
        raise RuntimeError(f"the procedure needs the OPR mounted on {where}, and this station has no operator")

    def align_interferometer(self, axis: str) -> None:
        raise RuntimeError(
            f"the procedure needs the interferometer aligned to {axis}, and this station has no operator"
        )


def default_operator(station: StationFile) -> Operator:
    choice = station.operator
    control = station.simulation.control if station.simulation else None
    if choice is None:
        choice = "simulation" if control else "console"
    if choice == "simulation":
        if control is None:
            raise ValueError("operator: simulation needs simulation.control {host, port} in the station file")
        return SimulationOperator(control.host, control.port)
    return ConsoleOperator() if choice == "console" else NoOperator()


Device = Robot | Camera | RotaryTable | Interferometer
DeviceT = TypeVar("DeviceT", Robot, Camera, RotaryTable, Interferometer)


class StationRuntime:
    """Devices of one station, built by the drivers' factories from the station's typed settings,
    opened on demand and closed together.

    Parameters
    ----------
    model : StationFile
    devices : mapping, optional
        Ready device objects by role (``robot``, ``camera:x`` ..., ``rotary_table``,
        ``interferometer``) instead of the factories: tests pass fakes here.
    operator : Operator, optional
    """

    def __init__(self, model: StationFile, *, devices: Mapping[str, Device] | None = None,
                 operator: Operator | None = None) -> None:
        self.model = model
        self.envelope = MotionEnvelope.from_dict(model.envelope.model_dump())
        self.reference_tcp_pose = np.asarray(model.frames.reference_tcp_pose, dtype=float)
        self._given: dict[str, Any] = dict(devices or {})
        self._open: dict[str, Any] = {}
        self.operator = operator if operator is not None else default_operator(model)

    def device(self, role: str) -> Device:
        """The opened device for ``role`` (opening it on first use)."""
        if role == "robot":
            return self.robot
        if role == "rotary_table":
            return self.table
        if role == "interferometer":
            return self.interferometer
        if role.startswith("camera:") and role.split(":", 1)[1] in SCREENS:
            return self.camera(role.split(":", 1)[1])
        raise DeviceConnectionError(role, "open", "no such device role (robot, camera:x|y|z, rotary_table, "
                                                  "interferometer)")

    @property
    def robot(self) -> Robot:
        # Commanded poses are OPR poses: the TCP is the OPR's nominal mounting on the flange.
        tcp = np.asarray(self.model.frames.tcp_offset, dtype=float)
        return self._opened("robot", self._make_robot, then=lambda robot: robot.set_tcp(tcp))

    def camera(self, screen: str) -> Camera:
        settings = getattr(self.model.devices.cameras, screen)
        return self._opened(f"camera:{screen}", lambda: drivers.camera.create(settings, name=f"camera:{screen}"))

    @property
    def table(self) -> RotaryTable:
        return self._opened("rotary_table", self._make_table)

    def camera_stream(self, rate_hz: float, **options: Any) -> Any:
        """Start streaming the three cameras together (``drivers.camera.CameraTriplet.start_stream``;
        ``options``: ``exposure_s``, ``roi``, ``timeout``). A ``camera_stream`` among the given devices
        (tests' fakes) is started instead."""
        given = self._given.get("camera_stream")
        if given is not None:
            return given.start_stream(rate_hz, **options)
        triplet = drivers.camera.CameraTriplet({s: self.camera(s) for s in SCREENS}, name="cameras")
        return triplet.start_stream(rate_hz, **options)

    @property
    def interferometer(self) -> Interferometer:
        return self._opened("interferometer", self._make_interferometer)

    def opened(self, role: str) -> Device | None:
        return self._open.get(role)

    # ------------------------------------------------------------------------------ building
    def _make_robot(self) -> Robot:
        # The robot checks every target against the station's envelope, not a default one.
        return drivers.robot.create(self.model.devices.robot, name="robot", envelope=self.envelope)

    def _make_table(self) -> RotaryTable:
        settings = self.model.devices.rotary_table
        if settings is None:
            raise DeviceConnectionError("rotary_table", "open", "the station file configures no rotary_table")
        return drivers.rotary_table.create(settings, name="rotary_table")

    def _make_interferometer(self) -> Interferometer:
        settings = self.model.devices.interferometer
        if settings is None:
            raise DeviceConnectionError("interferometer", "open", "the station file configures no interferometer")
        return drivers.interferometer.create(settings, name="interferometer")

    def _opened(self, role: str, make: Callable[[], DeviceT],
                then: Callable[[DeviceT], None] | None = None) -> DeviceT:
        """The device for ``role``: built (or taken from the given ones), opened and passed to
        ``then`` on first use; any failure is a ``DeviceError`` naming the role."""
        if role in self._open:
            device: DeviceT = self._open[role]
            return device
        device = self._given[role] if role in self._given else make()
        try:
            device.open()
            if then is not None:
                then(device)
        except DeviceError:
            raise
        except Exception as exc:
            raise DeviceConnectionError(role, "open", f"{type(exc).__name__}: {exc}") from exc
        self._open[role] = device
        return device

    # ------------------------------------------------------------------------------ shutting down
    def safe_state(self) -> list[str]:
        """Stop the robot and the table (whatever is open); returns problems, never raises."""
        problems = []
        for role in ("robot", "rotary_table"):
            device = self._open.get(role)
            if device is None:
                continue
            try:
                device.stop()
            except Exception as exc:
                problems.append(f"{role}: stop failed: {exc}")
        return problems

    def close(self) -> None:
        for device in reversed(list(self._open.values())):
            try:
                device.close()
            except Exception:
                pass
        self._open.clear()
