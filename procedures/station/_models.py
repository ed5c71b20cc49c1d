"""The station file format and the hooks, as pydantic models (the single source of the schemas).

Units are in the field names. Inside the code everything is SI. The procedure files' models live
with their kinds, in ``procedures/kinds/``.
"""

from __future__ import annotations

import ipaddress
import math
from typing import Annotated, Any, Literal, get_args
from urllib.parse import urlparse

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from drivers.camera import CameraSettings
from drivers.interferometer import InterferometerSettings
from drivers.robot import RobotSettings
from drivers.rotary_table import RotaryTableSettings

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3, description="three numbers")]
Pose6 = Annotated[
    list[float],
    Field(min_length=6, max_length=6, description="[x, y, z, rx, ry, rz]: metres and rotation vector (rad)"),
]
Event = Literal[
    "run_started", "run_paused", "run_resumed", "run_finished", "run_failed", "run_aborted", "point_measured"
]


def _every_event() -> list[Event]:
    return list(get_args(Event))


class _Strict(BaseModel):
    # Unknown keys are typos; NaN and infinity are never a setting (a NaN target passes every `<` check).
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


def _finite_numbers(value: Any, where: str = "") -> str | None:
    """The path of the first NaN or infinite number inside ``value`` (mappings and lists), or None."""
    if isinstance(value, float) and not math.isfinite(value):
        return where or "(value)"
    if isinstance(value, dict):
        items: Any = value.items()
    elif isinstance(value, list):
        items = enumerate(value)
    else:
        return None
    for key, item in items:
        found = _finite_numbers(item, f"{where}[{key!r}]" if isinstance(key, int) else f"{where}.{key}")
        if found:
            return found
    return None


# ------------------------------------------------------------------------------------------ hooks
class HookSpec(_Strict):
    """One hook: exactly one of ``call``, ``entry_point``, ``shell``, ``http``."""

    events: list[Event] = Field(default_factory=_every_event, description="events that trigger the hook")
    call: str | None = Field(
        None, description="a Python callable 'package.module:function', called with the event dict"
    )
    entry_point: str | None = Field(None, description="name of an entry point in group 'opr_instrument.hooks'")
    shell: str | None = Field(None, description="a shell command; the event JSON is on stdin and in $INSTRUMENT_EVENT")
    http: str | None = Field(
        None, description="a loopback URL (http://127.x.x.x:port/path) that receives a POST of the event JSON"
    )
    timeout_s: float = Field(10.0, gt=0, le=600, description="seconds before the hook is abandoned")

    @model_validator(mode="before")
    @classmethod
    def _yaml_on_key(cls, data: Any) -> Any:
        # YAML 1.1 reads an unquoted ``on:`` key as the boolean True; take it as ``events``.
        if isinstance(data, dict) and True in data and "events" not in data:
            data = {("events" if k is True else k): v for k, v in data.items()}
        return data

    @model_validator(mode="after")
    def _exactly_one(self) -> HookSpec:
        given = [k for k in ("call", "entry_point", "shell", "http") if getattr(self, k)]
        if len(given) != 1:
            raise ValueError(f"a hook needs exactly one of call, entry_point, shell, http (got {given or 'none'})")
        return self

    @field_validator("call")
    @classmethod
    def _module_function(cls, value: str | None) -> str | None:
        if value is not None and (":" not in value or not all(value.split(":", 1))):
            raise ValueError(f"expected 'package.module:function', got {value!r}")
        return value

    @field_validator("http")
    @classmethod
    def _loopback(cls, value: str | None) -> str | None:
        if value is None:
            return value
        url = urlparse(value)
        if url.scheme != "http" or not url.hostname:
            raise ValueError(f"expected an http:// URL, got {value!r}")
        host = "127.0.0.1" if url.hostname == "localhost" else url.hostname
        try:
            loopback = ipaddress.ip_address(host).is_loopback
        except ValueError:
            loopback = False
        if not loopback:
            raise ValueError(f"hooks post to loopback addresses only (127.0.0.0/8), got {url.hostname!r}")
        return value


# ---------------------------------------------------------------------------------------- station
class CamerasConfig(_Strict):
    """The three screen cameras, each with its adapter's settings."""

    x: CameraSettings
    y: CameraSettings
    z: CameraSettings


class DevicesConfig(_Strict):
    """Each device's adapter (``adapter:``) and that adapter's settings, validated by the drivers' models."""

    robot: RobotSettings
    cameras: CamerasConfig
    rotary_table: RotaryTableSettings | None = None
    interferometer: InterferometerSettings | None = None


class FramesConfig(_Strict):
    reference_tcp_pose: Pose6 = Field(description="TCP pose (base) at which the OPR sits at M's origin")
    tcp_offset: Pose6 = Field(description="nominal OPR mounting on the flange, set as the robot's TCP")
    tool_in_opr: Pose6 = Field(description="nominal ISO measuring point in the OPR frame")


class EnvelopeConfig(_Strict):
    box_min: Vec3 = Field(description="TCP position lower limits, base frame, metres")
    box_max: Vec3 = Field(description="TCP position upper limits, base frame, metres")
    reference_rotvec: Vec3 = Field(description="reference tool orientation, rotation vector (rad)")
    max_tilt: float = Field(math.pi, gt=0, le=math.pi, description="largest rotation from the reference, rad")
    max_speed: float = Field(0.5, gt=0, description="m/s")
    max_acceleration: float = Field(2.0, gt=0, description="m/s²")
    max_joint_speed: float = Field(1.5, gt=0, description="rad/s")
    max_joint_acceleration: float = Field(3.0, gt=0, description="rad/s²")

    @model_validator(mode="after")
    def _ordered(self) -> EnvelopeConfig:
        if any(lo >= hi for lo, hi in zip(self.box_min, self.box_max)):
            raise ValueError(f"box_min must be below box_max on every axis (got {self.box_min} / {self.box_max})")
        return self


class RatedConfig(_Strict):
    """The robot's rated values (its data sheet), for the ISO 9283 test conditions: each optional."""

    speed: float | None = Field(None, gt=0, description="rated TCP speed, m/s")
    acceleration: float | None = Field(None, gt=0, description="rated TCP acceleration, m/s²")
    payload: float | None = Field(None, gt=0, description="rated payload, kg")
    stabilisation_band: float | None = Field(None, gt=0, le=0.01, description="the manufacturer's pose "
                                             "stabilisation band, m (ISO 9283 7.4; iso9283_stabilisation's default)")


class CalibrationConfig(_Strict):
    record: str | list[str] | None = Field(
        None, description="calibration record file(s) in force (JSON): one path, a list (e.g. a displacement and "
        "an angle record, each correcting its own components, applied in order), or null"
    )


class ControlEndpoint(_Strict):
    host: str = "127.0.0.1"
    port: int = Field(ge=1, le=65535)


class SimulationConfig(BaseModel):
    """Present only for a simulated cell (written by ``sim_devices.cell.SimCell``)."""

    model_config = ConfigDict(extra="allow")
    control: ControlEndpoint | None = None
    truth_log: str | None = Field(None, description="ground-truth JSON-lines log of the simulated world")
    earlier_truth_logs: list[str] = Field(
        default_factory=list, description="truth logs of the cells a resumed run was measured on before this one "
        "(kept by the engine, so a report keeps the truth of every sample)")


class StationFile(_Strict):
    name: str
    devices: DevicesConfig
    geometry: dict[str, Any] = Field(description="screen geometry, read by instrument.pose.Geometry.from_dict")

    @field_validator("geometry")
    @classmethod
    def _finite_geometry(cls, value: dict[str, Any]) -> dict[str, Any]:
        where = _finite_numbers(value)
        if where:
            raise ValueError(f"expected finite numbers; {where.lstrip('.')} is NaN or infinite")
        return value

    frames: FramesConfig
    envelope: EnvelopeConfig
    rated: RatedConfig | None = Field(None, description="the robot's rated speed, acceleration and payload (ISO "
                                      "9283 tests at rated values; the report gives the run's as a percentage)")
    calibration: CalibrationConfig = Field(default_factory=CalibrationConfig)
    simulation: SimulationConfig | None = None
    hooks: list[HookSpec] = Field(default_factory=list)
    operator: Literal["console", "simulation", "none"] | None = Field(
        None, description="who re-mounts the OPR and aligns the interferometer; default: simulation when "
        "a simulation.control endpoint is given, else console"
    )
