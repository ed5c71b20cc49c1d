"""The robot's settings in a station file: one model per adapter, discriminated on ``adapter``.

The motion envelope is not a robot setting: it belongs to the station (its ``envelope`` section)
and is handed to ``create`` as a ``MotionEnvelope``, so the driver refuses exactly what the
station refuses.
"""

from __future__ import annotations

import ipaddress
from typing import Annotated, Literal
from urllib.parse import urlsplit

from pydantic import Field, field_validator, model_validator

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


class ABBRwsSettings(DeviceSettings):
    """An ABB IRC5 controller (RobotWare 6) through Robot Web Services and EGM (``ABBRobot``)."""

    adapter: Literal["abb_rws"] = Field("abb_rws", description="this adapter: ABB IRC5 through RWS 1.0 and EGM")
    base_url: str = Field("http://127.0.0.2:80", description="the controller's RWS address (its WAN port), "
                          "http://host[:port]")
    username: str = Field("Default User", min_length=1, description="RWS user (HTTP Digest)")
    password: str = Field("robotics", description="RWS password")
    mechanical_unit: str = Field("ROB_1", min_length=1, description="the robot's mechanical unit")
    task: str = Field("T_ROB1", min_length=1, description="the RAPID motion task running motion_program_exec")
    tool: str = Field("motion_program_tool", min_length=1,
                      description="the tooldata the motion programs set (TCP and load); poses are read with it")
    wobj: str = Field("wobj0", min_length=1, description="work object for reading poses (in the base frame)")
    egm_host: str | None = Field(None, description="address the EGM socket binds (default: the base URL's host "
                                 "if it is a loopback address, else 127.0.0.1)")
    egm_port: int = Field(6510, gt=0, lt=65536, description="UDP port the controller's EGM stream (UCdevice) "
                          "is sent to")
    egm_remote: bool = Field(False, description="allow egm_host to be a non-loopback address (a controller on "
                             "the network)")
    connect_timeout: float = Field(5.0, gt=0, description="seconds to reach RWS and for the first EGM packet")
    command_timeout: float = Field(10.0, gt=0, description="seconds for any HTTP request and any call that is "
                                   "not a motion")
    move_timeout: float = Field(120.0, gt=0, description="seconds a blocking move may take (a call may override it)")
    stale_timeout: float = Field(2.0, gt=0, description="seconds without an EGM packet after which the "
                                 "connection counts as lost")
    unchecked_joint_moves: bool = Field(False, description="allow move_joint although its TCP target cannot be "
                                        "checked against the envelope (RWS 1.0 has no forward kinematics)")

    @field_validator("base_url")
    @classmethod
    def _http_url(cls, value: str) -> str:
        parts = urlsplit(value)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError(f"base_url must be http://host[:port], got {value!r}")
        return value.rstrip("/")

    @model_validator(mode="after")
    def _egm_on_loopback(self) -> ABBRwsSettings:
        if self.egm_host is not None and not self.egm_remote:
            try:
                loopback = ipaddress.ip_address(self.egm_host).is_loopback
            except ValueError:
                loopback = False
            if not loopback:
                raise ValueError(f"egm_host {self.egm_host!r} is not a loopback address (127.0.0.0/8); set "
                                 "egm_remote: true to bind the EGM socket on the network")
        return self


# The union is the seam each controller family is added to.
RobotSettings = Annotated[URRtdeSettings | ABBRwsSettings, Field(discriminator="adapter")]
