"""The station's motion envelope: checked before any motion is sent to a controller."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivers._errors import MotionRefused


@dataclass(frozen=True)
class MotionEnvelope:
    """Box and orientation limits for TCP targets, and speed/acceleration caps.

    Attributes
    ----------
    box_min, box_max : (3,) arrays
        TCP position limits in the base frame, metres.
    reference_rotvec : (3,) array
        The reference tool orientation (rotation vector).
    max_tilt : float
        Largest allowed rotation of a target away from ``reference_rotvec``, radians.
    max_speed, max_acceleration : float
        Caps for linear moves, m/s and m/s².
    max_joint_speed, max_joint_acceleration : float
        Caps for joint moves, rad/s and rad/s².
    """

    box_min: np.ndarray = field(default_factory=lambda: np.array([-1.0, -1.0, -1.0]))
    box_max: np.ndarray = field(default_factory=lambda: np.array([1.0, 1.0, 1.0]))
    reference_rotvec: np.ndarray = field(default_factory=lambda: np.array([np.pi, 0.0, 0.0]))
    max_tilt: float = np.pi
    max_speed: float = 0.5
    max_acceleration: float = 2.0
    max_joint_speed: float = 1.5
    max_joint_acceleration: float = 3.0

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> MotionEnvelope:
        """The envelope from a station file's ``envelope`` mapping (field names as above, SI units)."""
        kwargs = dict(data)
        for key in ("box_min", "box_max", "reference_rotvec"):
            if key in kwargs:
                kwargs[key] = np.asarray(kwargs[key], dtype=float).reshape(3)
        return cls(**kwargs)

    def check_pose(self, pose: np.ndarray, device: str = "robot") -> None:
        """Raise ``MotionRefused`` if ``pose`` ([x, y, z, rx, ry, rz]) lies outside the envelope."""
        from scipy.spatial.transform import Rotation
        pose = np.asarray(pose, dtype=float)
        if pose.shape != (6,) or not np.all(np.isfinite(pose)):
            raise MotionRefused(device, "check target", f"target must be 6 finite numbers, got {pose!r}")
        position = pose[:3]
        low = position < self.box_min
        high = position > self.box_max
        if low.any() or high.any():
            axis = "xyz"[int(np.flatnonzero(low | high)[0])]
            raise MotionRefused(
                device,
                "check target",
                f"TCP {axis} = {position['xyz'.index(axis)] * 1e3:.3f} mm is outside the envelope "
                f"[{self.box_min['xyz'.index(axis)] * 1e3:.3f}, {self.box_max['xyz'.index(axis)] * 1e3:.3f}] mm",
            )
        tilt = (Rotation.from_rotvec(self.reference_rotvec).inv() * Rotation.from_rotvec(pose[3:])).magnitude()
        if tilt > self.max_tilt:
            raise MotionRefused(
                device,
                "check target",
                f"orientation is {np.degrees(tilt):.3f}° from the reference, limit {np.degrees(self.max_tilt):.3f}°",
            )

    def check_speed(self, speed: float, acceleration: float, *, joint: bool = False, device: str = "robot") -> None:
        """Raise ``MotionRefused`` if a speed or acceleration exceeds its cap or is not positive."""
        cap_v = self.max_joint_speed if joint else self.max_speed
        cap_a = self.max_joint_acceleration if joint else self.max_acceleration
        unit = "rad/s" if joint else "m/s"
        if not (np.isfinite(speed) and 0 < speed <= cap_v):
            raise MotionRefused(device, "check speed", f"speed {speed} {unit} is not in (0, {cap_v}] {unit}")
        if not (np.isfinite(acceleration) and 0 < acceleration <= cap_a):
            raise MotionRefused(
                device, "check acceleration", f"acceleration {acceleration} {unit}/s is not in (0, {cap_a}] {unit}/s"
            )
