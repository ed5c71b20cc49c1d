"""The robot's settings in a station file: one model per adapter, discriminated on ``adapter``.

The motion envelope is not a robot setting: it belongs to the station (its ``envelope`` section)
and is handed to ``create`` as a ``MotionEnvelope``, so the driver refuses exactly what the
station refuses.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from drivers._settings import DeviceSettings


class URRtdeSettings(DeviceSettings):
    """A Universal Robots e-Series controller through ``ur_rtde`` (``URRobot``)."""

    adapter: Literal["ur_rtde"] = Field("ur_rtde", description="this adapter: UR controllers through ur_rtde")
    host: str = Field(
        "127.0.0.2", min_length=1, description="controller address; the UR ports 30004/29999/30003 are fixed"
    )
    frequency: float = Field(500.0, gt=0, le=500, description="RTDE output frequency, Hz (500 on e-Series)")
    connect_timeout: float = Field(
        5.0, gt=0, description="seconds for each step of the connection probe and for the clients' handshakes"
    )
    command_timeout: float = Field(
        10.0, gt=0, description="seconds for any call that is not a motion (setTcp, queries, stop, disconnect)"
    )
    move_timeout: float = Field(120.0, gt=0, description="seconds a blocking move may take (a call may override it)")
    stale_timeout: float = Field(
        2.0, gt=0, description="seconds without a new RTDE timestamp after which the connection counts as lost"
    )
    upper_range_registers: bool = Field(
        False, description="use RTDE registers 24-47 (when 0-23 belong to a fieldbus)"
    )


# One adapter today; the union is the seam a second controller family is added to.
RobotSettings = Annotated[URRtdeSettings, Field(discriminator="adapter")]
