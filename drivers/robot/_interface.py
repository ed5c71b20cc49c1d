"""The robot interface every adapter implements.

Poses are TCP poses in the robot base frame as ``(6,)`` arrays ``[x, y, z, rx, ry, rz]``: metres
and a rotation vector (axis times angle, radians), the convention of UR controllers. Joint
positions are ``(6,)`` arrays in radians. Speeds are m/s (linear) or rad/s (joint).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from drivers._errors import DeviceError, DeviceFault


class ProtectiveStop(DeviceFault):
    """The controller is in protective stop; motion is impossible until it is cleared."""


class EmergencyStop(DeviceFault):
    """The emergency stop is engaged."""


class ProgramStopped(DeviceFault):
    """The controller's program (the control script) is not running."""


class MoveFailed(DeviceError):
    """A move did not complete (stopped, rejected by the controller, or did not reach its target)."""


@dataclass(frozen=True)
class RobotState:
    """A snapshot of the controller's state."""

    connected: bool
    protective_stop: bool
    emergency_stop: bool
    program_running: bool
    steady: bool
    robot_mode: int = -1
    safety_mode: int = -1


@dataclass(frozen=True)
class RobotIdentity:
    """Who the controller says it is: the robot's part of the ISO 9283 test conditions.

    Attributes
    ----------
    manufacturer : str
        E.g. ``"Universal Robots"``.
    model : str
        The controller's answer for the arm's model, e.g. ``"UR5"``.
    serial_number : str
        The robot's serial number, as the controller reports it.
    controller_version : str
        Controller software version, e.g. ``"5.15.0.0"`` (PolyScope).
    """

    manufacturer: str
    model: str
    serial_number: str
    controller_version: str


@runtime_checkable
class Robot(Protocol):
    """One robot controller. Every call that waits takes or has a timeout."""

    name: str

    def open(self) -> None:
        """Connect (every wait bounded); raises ``DeviceConnectionError`` or ``DeviceTimeout``."""
        ...

    def close(self) -> None:
        """Release the connection (also after a failed or no ``open()``; calling it twice is harmless)."""
        ...

    def __enter__(self) -> Robot: ...

    def __exit__(self, *exc: object) -> None: ...

    def tcp_pose(self) -> np.ndarray:
        """Actual TCP pose ``[x, y, z, rx, ry, rz]`` in the base frame."""
        ...

    def joint_positions(self) -> np.ndarray: ...

    def move_linear(
        self,
        pose: np.ndarray,
        speed: float = 0.25,
        acceleration: float = 1.2,
        *,
        asynchronous: bool = False,
        timeout: float | None = None,
    ) -> None:
        """Linear move to ``pose``. Checks the envelope first (raises ``MotionRefused``); a
        protective stop or lost connection during the move raises its typed error."""
        ...

    def move_joint(
        self,
        joints: np.ndarray,
        speed: float = 1.05,
        acceleration: float = 1.4,
        *,
        asynchronous: bool = False,
        timeout: float | None = None,
    ) -> None: ...

    def move_path(
        self,
        poses: np.ndarray,
        speed: float | Sequence[float] = 0.25,
        acceleration: float | Sequence[float] = 1.2,
        blend_radius: float | Sequence[float] = 0.0,
        *,
        asynchronous: bool = False,
        timeout: float | None = None,
    ) -> None:
        """Linear moves through the waypoints ``poses`` (n, 6), corners rounded by ``blend_radius`` (m)."""
        ...

    def move_circular(
        self,
        via: np.ndarray,
        to: np.ndarray,
        speed: float = 0.25,
        acceleration: float = 1.2,
        *,
        blend_radius: float = 0.0,
        timeout: float | None = None,
    ) -> None:
        """Circular move(s) from the current pose through ``via`` to ``to`` ((6,) or (n, 6) for n arcs)."""
        ...

    def stop(self, deceleration: float = 2.0) -> None: ...

    def wait_until_steady(self, timeout: float = 10.0) -> None: ...

    def is_steady(self) -> bool:
        """The controller's own view: its encoders at rest (the tool may still ring)."""
        ...

    def controller_time(self) -> float:
        """The controller's clock, s (UR: the RTDE ``timestamp`` of the latest package)."""
        ...

    def last_move_done_time(self) -> float | None:
        """Controller time at which the last blocking move was reported done (None before one)."""
        ...

    def set_tcp(self, offset: np.ndarray) -> None: ...

    def tcp_offset(self) -> np.ndarray: ...

    def state(self) -> RobotState: ...

    def identity(self) -> RobotIdentity:
        """Manufacturer, model, serial number and controller version, read from the controller."""
        ...

    def set_payload(self, mass_kg: float, cog_m: Sequence[float]) -> None:
        """Set the payload mass (kg) and centre of gravity (m, tool flange frame) on the controller."""
        ...
