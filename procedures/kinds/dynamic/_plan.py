"""What the two kinds that measure in motion share: their parameters, the cube's points and paths,
the session start, and one measured move (``iso9283_stabilisation``, ``iso9283_path``).

Speeds are percentages of the robot's rated speed (the station's ``rated.speed``, else its
envelope's ``max_speed``); accelerations of the envelope's ``max_acceleration``. Positions are the
OPR's in nominal M (metres), turned into TCP poses at the reference orientation.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import Field

from instrument.iso9283 import iso_cube_points
from procedures.kinds._approach import pose_directions
from procedures.kinds._conditions import SessionRecord, operator_of, robot_identity, set_payload
from procedures.kinds._parameters import MotionParameters
from procedures.kinds._protocol import PoseReading, Reading, Step, StepContext
from procedures.kinds._setups import OprOnRobot
from procedures.station import StationFile, Vec3, translated_in_frame
from procedures.store import CorrectedPose, PoseQuality, Reference, SessionConditions, SolvedPose, as_pose

CYCLE_ORDER = ("P1", "P5", "P4", "P3", "P2")  # ISO 9283's cycle; each pose is approached from the one before it
Point = Sequence[float] | np.ndarray  # a position in M (m)
MIN_SAMPLES = 10  # a move with fewer poses than this is a failed sample (measured again on resume)


def _paper_cube_center() -> list[float]:
    return [0.035, 0.035, 0.035]


def _no_offset() -> list[float]:
    return [0.0, 0.0, 0.0]


def _iso_speeds() -> list[float]:
    return [100.0, 50.0, 10.0]


class DynamicParameters(MotionParameters):
    """Parameters both kinds share (the YAML's ``parameters``; units in the names)."""

    cube_center_m: Vec3 = Field(default_factory=_paper_cube_center, description="cube centre in M, metres")
    cube_edge_m: float = Field(0.07, gt=0, le=2.0, description="cube edge, metres")
    cycles: int = Field(3, ge=2, le=1000, description="cycles per speed")
    speeds_percent: list[float] = Field(default_factory=_iso_speeds, min_length=1, max_length=10,
                                        description="measured speeds, % of the rated speed (station rated.speed, "
                                        "else envelope max_speed); ISO 9283: 100, 50, 10")
    apply_compensation: bool = Field(True, description="correct the streamed poses with the calibration record(s) "
                                     "in force, as the static kinds do")
    payload_mass_kg: float | None = Field(None, ge=0, le=2000, description="payload mass, kg, set on the robot at "
                                          "the start of every session (ISO 9283: the rated payload); null: not set")
    payload_cog_m: Vec3 = Field(default_factory=_no_offset, description="payload centre of gravity in the tool "
                                "flange frame, metres")
    rate_hz: float = Field(100.0, gt=0, le=2000, description="camera trigger rate while streaming, Hz")
    exposure_s: float = Field(0.001, gt=0, lt=0.1, description="exposure of each streamed frame, s")
    rest_s: float = Field(0.5, ge=0, le=30, description="wait before each measured move, s (the ring-down of the "
                          "move to its start dies out)")
    min_poses: int = Field(MIN_SAMPLES, ge=3, le=100000, description="fewest streamed poses of a move; fewer: the "
                           "move's sample failed (measured again on resume)")


def settings_title(what: str, parameters: Mapping[str, Any]) -> str:
    """The report's title of a run measured in motion: what it measured, its cycles and speeds as run
    (e.g. "ISO 9283 pose stabilisation — 2 cycles at 100, 20 % of rated speed")."""
    cycles, speeds = parameters.get("cycles"), parameters.get("speeds_percent")
    if not isinstance(cycles, int) or not isinstance(speeds, list):
        return what
    return (f"{what} — {cycles} cycle{'s' if cycles != 1 else ''} at "
            f"{', '.join(f'{s:g}' for s in speeds)} % of rated speed")


def cube_point(params: DynamicParameters, label: str) -> np.ndarray:
    """P1…P5 of the ISO cube, in nominal M (m)."""
    cube = iso_cube_points(np.asarray(params.cube_center_m, dtype=float), float(params.cube_edge_m))
    return np.asarray(cube.points[label], dtype=float)


def tcp_at(station: StationFile, point_in_m: Point) -> list[float]:
    """The commanded TCP pose (base frame) that puts the OPR at ``point_in_m`` at the reference orientation."""
    return [float(v) for v in translated_in_frame(station.frames.reference_tcp_pose, point_in_m)]


def rated_speed(station: StationFile) -> float:
    """m/s: the station's rated speed, else its envelope's cap."""
    if station.rated is not None and station.rated.speed is not None:
        return float(min(station.rated.speed, station.envelope.max_speed))
    return float(station.envelope.max_speed)


def motion_of(station: StationFile, params: DynamicParameters, speed_percent: float) -> tuple[float, float]:
    """(speed m/s, acceleration m/s²) of a measured move."""
    speed = rated_speed(station) * speed_percent / 100.0
    acceleration = station.envelope.max_acceleration * params.acceleration_percent / 100.0
    return float(min(speed, station.envelope.max_speed)), float(acceleration)


def robot_step(index: int, key: str, phase: str, station: StationFile, target_in_m: Point,
               start_in_m: Point | None, label: str, meta: dict[str, Any],
               waypoints_in_m: Sequence[Point] = ()) -> Step:
    """A step whose measured motion ends at ``target_in_m``, starting from ``start_in_m`` (checked by
    the dry run as ``via``, with every waypoint)."""
    via = tuple(tcp_at(station, p) for p in ([start_in_m] if start_in_m is not None else []) + list(waypoints_in_m))
    return Step(index=index, key=key, phase=phase, setup=OprOnRobot(), tcp_pose=tcp_at(station, target_in_m),
                label=label, via=via,
                meta={**meta, "position_in_m": [float(v) for v in target_in_m],
                      "start_in_m": None if start_in_m is None else [float(v) for v in start_in_m]})


@dataclass
class DynamicSession:
    """What one session of a run measured in motion remembers: the TCP pose the robot was last sent to
    (None: unknown, as after a measured motion, whose end the next step does not assume)."""

    last_tcp: list[float] | None = None


def start_session(ctx: StepContext, params: DynamicParameters) -> None:
    """Identity, payload and operator at the start of this session (recorded with its first sample)."""
    record = ctx.session_state(SessionRecord)
    if record.conditions is not None:
        return
    started = time.time()
    robot = robot_identity(ctx)
    payload = set_payload(ctx, params.payload_mass_kg, params.payload_cog_m)
    record.start(SessionConditions(started=started, robot=robot, payload=payload,
                                   warm_up={"mode": "declared", "duration_s": 0.0},
                                   operator=operator_of(params.operator)))


def go_to(ctx: StepContext, tcp_pose: Sequence[float]) -> None:
    """Move (at the run's repositioning speed) unless the robot is already there."""
    state = ctx.session_state(DynamicSession)
    if state.last_tcp != list(tcp_pose):
        ctx.move_robot(tcp_pose)
        state.last_tcp = list(tcp_pose)


def approach_direction(step: Step) -> dict[str, int | None]:
    """Per component, the side the measured motion arrives from (for the records' hysteresis)."""
    start = step.meta.get("start_in_m")
    end = step.meta["position_in_m"]
    previous = None if start is None else [*start, 0.0, 0.0, 0.0]
    return pose_directions(previous, [*end, 0.0, 0.0, 0.0])


def stream_reading(step: Step, params: DynamicParameters, ctx: StepContext, record: Any,
                   figures: dict[str, Any], error: str | None) -> Reading:
    """The sample of a measured move: its settled pose (the mean of the stream's last fifth), the move's
    figures, the stream itself (stored with the sample); failed when ``error``."""
    summary = {"poses": len(record), "triggers": record.meta.get("triggers"), "dropped": record.dropped,
               "drop_reasons": record.meta.get("drop_reasons"), "t_signal": record.meta.get("t_signal"),
               "clock": record.meta.get("clock")}
    reference = Reference(robot_tcp_pose=as_pose(ctx.robot.tcp_pose()), approach=approach_direction(step),
                          readings={"stream": summary, "dynamic": figures})
    session = ctx.session_state(SessionRecord).take()
    if error is not None:
        return Reading(pose=PoseReading(ok=False, error=error, attempts=1), reference=reference, stream=record,
                       session=session)
    tail = max(3, len(record) // 5)
    quality = PoseQuality(residual_rms=float(np.mean(record.residual_rms[-tail:])),
                          pose_std=as_pose(record.raw[-tail:].std(axis=0)), attempts=1)
    solved = SolvedPose(pose=as_pose(record.raw[-tail:].mean(axis=0)), quality=quality)
    corrected = None
    if params.apply_compensation and not np.allclose(record.pose, record.raw):
        corrected = CorrectedPose(pose=as_pose(record.pose[-tail:].mean(axis=0)), direction=approach_direction(step))
    return Reading(pose=PoseReading(ok=True, solved=solved, corrected=corrected, t_measured=time.time(), attempts=1),
                   reference=reference, stream=record, session=session)


def stream_problem(record: Any, params: DynamicParameters) -> str | None:
    """Why a move's stream cannot give its figures (None: it can)."""
    if len(record) < params.min_poses:
        reasons = ", ".join(f"{k}: {v}" for k, v in (record.meta.get("drop_reasons") or {}).items()) or "none given"
        return (f"stream: {len(record)} poses of {record.meta.get('triggers')} triggers (fewer than min_poses = "
                f"{params.min_poses}; drops: {reasons})")
    signal = record.meta.get("t_signal")
    if signal is None:
        return "stream: the robot gave no done signal (last_move_done_time)"
    if not record.t[0] <= signal <= record.t[-1]:
        return (f"stream: the robot's done signal ({signal:.3f} s) lies outside the streamed poses "
                f"({record.t[0]:.3f}–{record.t[-1]:.3f} s)")
    return None


Segment = Literal["line", "circle"]
