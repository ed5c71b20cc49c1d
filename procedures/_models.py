"""The station and procedure file formats, as pydantic models (the single source of the schemas).

Units are in the field names. Inside the code everything is SI; the few operator-friendly fields
in mm or degrees are converted by the ``*_si`` properties, at the edge.
"""

from __future__ import annotations

import ipaddress
import math
from typing import Annotated, Any, Literal
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
AxisName = Literal["x", "y", "z"]
EVENTS = ("run_started", "run_paused", "run_resumed", "run_finished", "run_failed", "run_aborted", "point_measured")
Event = Literal[
    "run_started", "run_paused", "run_resumed", "run_finished", "run_failed", "run_aborted", "point_measured"
]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


# ------------------------------------------------------------------------------------------ hooks
class HookSpec(_Strict):
    """One hook: exactly one of ``call``, ``entry_point``, ``shell``, ``http``."""

    events: list[Event] = Field(default_factory=lambda: list(EVENTS), description="events that trigger the hook")
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


class StationFile(_Strict):
    name: str
    devices: DevicesConfig
    geometry: dict[str, Any] = Field(description="screen geometry, read by instrument.pose.Geometry.from_dict")
    frames: FramesConfig
    envelope: EnvelopeConfig
    calibration: CalibrationConfig = Field(default_factory=CalibrationConfig)
    simulation: SimulationConfig | None = None
    hooks: list[HookSpec] = Field(default_factory=list)
    operator: Literal["console", "simulation", "none"] | None = Field(
        None, description="who re-mounts the OPR and aligns the interferometer; default: simulation when "
        "a simulation.control endpoint is given, else console"
    )


# ------------------------------------------------------------------------------------- procedures
class MotionParameters(_Strict):
    speed_percent: float = Field(50.0, gt=0, le=100, description="robot linear speed, % of the envelope's max_speed")
    acceleration_percent: float = Field(50.0, gt=0, le=100, description="% of the envelope's max_acceleration")
    settle_time_s: float = Field(0.5, ge=0, le=60, description="wait after a move before measuring, s")
    move_timeout_s: float = Field(60.0, gt=0, le=600, description="longest allowed move, s")
    frames_per_pose: int = Field(3, ge=1, le=100, description="camera frame triples averaged per pose")
    grab_timeout_s: float = Field(5.0, gt=0, le=120, description="per frame, s")
    retries_per_pose: int = Field(2, ge=0, le=10, description="re-measurements of a pose whose frames fail")
    max_failed_samples: int = Field(3, ge=0, description="failed poses tolerated before the run fails")
    save_frames: Literal["never", "failed", "always"] = Field("failed", description="which raw frames to keep")


class DisplacementParameters(MotionParameters):
    axes: list[AxisName] = Field(default_factory=lambda: ["x", "y", "z"], min_length=1)
    start_mm: float = Field(0.0, description="first calibration point along the axis, mm")
    stop_mm: float = Field(70.0, description="last calibration point (inclusive), mm")
    step_mm: float = Field(5.0, gt=0, description="spacing of the points, mm")
    repeats: int = Field(3, ge=1, le=100, description="passes over the points per group")
    groups: int = Field(3, ge=1, le=20, description="groups, each from its own start pose")
    group_start_offsets_mm: list[Vec3] = Field(
        default_factory=lambda: [[0.0, 0.0, 0.0], [0.5, 0.5, 0.5], [-0.5, -0.5, -0.5]],
        description="per group, offset (mm, in M) of the whole line from M's origin",
    )
    interferometer_average_s: float = Field(0.5, gt=0, le=60, description="averaging window, s")
    record_path: str | None = Field(
        None, description="where to write the calibration record (default: in the run folder)"
    )

    @model_validator(mode="after")
    def _consistent(self) -> DisplacementParameters:
        if self.stop_mm <= self.start_mm:
            raise ValueError(f"stop_mm ({self.stop_mm}) must be above start_mm ({self.start_mm})")
        if len(self.group_start_offsets_mm) != self.groups:
            raise ValueError(f"groups is {self.groups} but group_start_offsets_mm has "
                             f"{len(self.group_start_offsets_mm)} entries: expected one offset per group")
        if len(set(self.axes)) != len(self.axes):
            raise ValueError(f"axes repeat an axis: {self.axes}")
        return self


class AngleParameters(MotionParameters):
    axes: list[AxisName] = Field(default_factory=lambda: ["x", "y", "z"], min_length=1)
    start_deg: float = Field(-1.0, description="first table angle, degrees")
    stop_deg: float = Field(1.0, description="last table angle (inclusive), degrees")
    step_deg: float = Field(0.25, gt=0, description="spacing, degrees")
    repeats: int = Field(3, ge=1, le=100)
    groups: int = Field(3, ge=1, le=20)
    group_start_offsets_deg: list[float] = Field(
        default_factory=lambda: [0.0, 0.1, -0.1], description="per group, offset of all angles, degrees"
    )
    table_speed_deg_s: float = Field(5.0, gt=0, le=360, description="rotary table speed, °/s")
    home_table: bool = Field(True, description="home the table before the first axis if it is not homed")
    record_path: str | None = None

    @model_validator(mode="after")
    def _consistent(self) -> AngleParameters:
        if self.stop_deg <= self.start_deg:
            raise ValueError(f"stop_deg ({self.stop_deg}) must be above start_deg ({self.start_deg})")
        if len(self.group_start_offsets_deg) != self.groups:
            raise ValueError(f"groups is {self.groups} but group_start_offsets_deg has "
                             f"{len(self.group_start_offsets_deg)} entries: expected one offset per group")
        if len(set(self.axes)) != len(self.axes):
            raise ValueError(f"axes repeat an axis: {self.axes}")
        return self


class IsoParameters(MotionParameters):
    cube_center_m: Vec3 = Field(default_factory=lambda: [0.035, 0.035, 0.035], description="cube centre in M, metres")
    cube_edge_m: float = Field(0.07, gt=0, le=2.0, description="cube edge, metres")
    cycles: int = Field(30, ge=2, le=10000, description="ISO 9283 cycles (the standard asks for 30)")
    transform_step: bool = Field(True, description="measure the cube once first and fit the robot↔M transform")
    apply_compensation: bool = Field(True, description="correct poses with the calibration record in force")


class _ProcedureBase(_Strict):
    name: str | None = None
    description: str = ""
    hooks: list[HookSpec] = Field(default_factory=list)


class DisplacementCalibration(_ProcedureBase):
    procedure: Literal["displacement_calibration"]
    parameters: DisplacementParameters = Field(default_factory=DisplacementParameters)


class AngleCalibration(_ProcedureBase):
    procedure: Literal["angle_calibration"]
    parameters: AngleParameters = Field(default_factory=AngleParameters)


class Iso9283Repeatability(_ProcedureBase):
    procedure: Literal["iso9283_repeatability"]
    parameters: IsoParameters = Field(default_factory=IsoParameters)


PROCEDURE_MODELS: dict[str, type[_ProcedureBase]] = {
    "displacement_calibration": DisplacementCalibration,
    "angle_calibration": AngleCalibration,
    "iso9283_repeatability": Iso9283Repeatability,
}
ProcedureFile = DisplacementCalibration | AngleCalibration | Iso9283Repeatability
