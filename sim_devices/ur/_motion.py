"""The UR twin's motions: ``sim_devices.arm.Motion`` with the UR5e arm unless told otherwise."""

from __future__ import annotations

from typing import Any

from sim_devices.arm import Motion as ArmMotion
from sim_devices.arm import Profile
from sim_devices.ur import _kinematics as kin

__all__ = ["Motion", "Profile"]


class Motion(ArmMotion):
    """A motion of the UR5e arm (see ``sim_devices.arm.Motion``)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("kinematics", kin.UR5E)
        super().__init__(*args, **kwargs)
