"""A station at run time: its devices (made by the driver factories), envelope and operator."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from drivers._errors import DeviceConnectionError, DeviceError
from drivers.robot._envelope import MotionEnvelope
from procedures._models import StationFile

_KIND_MODULE = {"robot": "drivers.robot", "camera": "drivers.camera", "rotary_table": "drivers.rotary_table",
                "interferometer": "drivers.interferometer"}
_OPEN_METHOD = {"robot": "connect", "camera": "open", "rotary_table": "connect", "interferometer": "open"}


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


def create_device(kind: str, config: Any, name: str, **extra: Any) -> Any:
    """``drivers.<kind>.create(config, name=name)`` (the cross-team factory contract); ``extra``
    settings that belong to the station rather than the device entry (the robot's envelope) are
    added to the device's configuration."""
    module = importlib.import_module(_KIND_MODULE[kind])
    factory = getattr(module, "create", None)
    if factory is None:
        raise DeviceConnectionError(name, "create", f"{_KIND_MODULE[kind]} has no create() factory yet")
    return factory({**config.model_dump(), **extra}, name=name)


class StationRuntime:
    """Devices of one station, opened on demand and closed together.

    Parameters
    ----------
    model : StationFile
    devices : dict, optional
        Ready device objects by role (``robot``, ``camera:x`` ..., ``rotary_table``,
        ``interferometer``) instead of the factories: tests pass fakes here.
    operator : Operator, optional
    """

    def __init__(self, model: StationFile, *, devices: dict[str, Any] | None = None,
                 operator: Operator | None = None) -> None:
        self.model = model
        self.envelope = MotionEnvelope.from_dict(model.envelope.model_dump())
        self.reference_tcp_pose = np.asarray(model.frames.reference_tcp_pose, dtype=float)
        self._given = dict(devices or {})
        self._open: dict[str, Any] = {}
        self.operator = operator if operator is not None else default_operator(model)

    def _config(self, role: str):
        devices = self.model.devices
        if role.startswith("camera:"):
            return "camera", getattr(devices.cameras, role.split(":")[1])
        config = getattr(devices, role)
        if config is None:
            raise DeviceConnectionError(role, "open", f"the station file configures no {role}")
        return role, config

    def device(self, role: str) -> Any:
        """The opened device for ``role`` (opening it on first use)."""
        if role in self._open:
            return self._open[role]
        if role in self._given:
            device = self._given[role]
        else:
            kind, config = self._config(role)
            # The robot checks every target against the station's envelope, not a default one.
            extra = {"envelope": self.model.envelope.model_dump()} if kind == "robot" else {}
            device = create_device(kind, config, name=role, **extra)
        kind = "camera" if role.startswith("camera:") else role
        try:
            getattr(device, _OPEN_METHOD[kind])()
            if kind == "robot":
                # Commanded poses are OPR poses: the TCP is the OPR's nominal mounting on the flange.
                device.set_tcp(np.asarray(self.model.frames.tcp_offset, dtype=float))
        except DeviceError:
            raise
        except Exception as exc:
            raise DeviceConnectionError(role, "open", f"{type(exc).__name__}: {exc}") from exc
        self._open[role] = device
        return device

    @property
    def robot(self) -> Any:
        return self.device("robot")

    def camera(self, screen: str) -> Any:
        return self.device(f"camera:{screen}")

    @property
    def table(self) -> Any:
        return self.device("rotary_table")

    @property
    def interferometer(self) -> Any:
        return self.device("interferometer")

    def opened(self, role: str) -> Any | None:
        return self._open.get(role)

    def safe_state(self) -> list[str]:
        """Stop the robot and the table (whatever is open); returns problems, never raises."""
        problems = []
        for role, stop in (("robot", lambda d: d.stop()), ("rotary_table", lambda d: d.stop())):
            device = self._open.get(role)
            if device is None:
                continue
            try:
                stop(device)
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
