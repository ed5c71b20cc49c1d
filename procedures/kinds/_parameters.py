"""What every procedure file shares: its frame (kind, name, hooks) and the motion parameters.

Units are in the field names; the few operator-friendly fields in mm or degrees are converted
to SI by each kind when it builds its plan.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from procedures.station import HookSpec

AxisName = Literal["x", "y", "z"]


def all_axes() -> list[AxisName]:
    """The default axes of a calibration: every axis of M."""
    return ["x", "y", "z"]


class _Strict(BaseModel):
    # Unknown keys are typos; NaN and infinity are never a setting (a NaN target passes every `<` check).
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class MotionParameters(_Strict):
    """Parameters every kind has: how the robot moves, how a pose is measured, what failure is tolerated."""

    speed_percent: float = Field(50.0, gt=0, le=100, description="robot linear speed, % of the envelope's max_speed")
    acceleration_percent: float = Field(50.0, gt=0, le=100, description="% of the envelope's max_acceleration")
    settle_time_s: float = Field(0.5, ge=0, le=60, description="wait after a move before measuring, s")
    move_timeout_s: float = Field(60.0, gt=0, le=600, description="longest allowed move, s")
    frames_per_pose: int = Field(3, ge=1, le=100, description="camera frame triples averaged per pose")
    grab_timeout_s: float = Field(5.0, gt=0, le=120, description="per frame, s")
    retries_per_pose: int = Field(2, ge=0, le=10, description="re-measurements of a pose whose frames fail")
    retry_backoff_s: float = Field(1.0, ge=0, le=10, description="wait before the first retry of a pose, s; "
                                   "doubled at each further retry, at most 10 s")
    max_failed_samples: int = Field(3, ge=0, le=100000, description="failed poses tolerated in one session of "
                                    "the run (a resume measures the failed ones again) before it fails")
    save_frames: Literal["never", "failed", "always"] = Field("failed", description="which raw frames to keep")
    plausibility_mm: float = Field(2.0, ge=0, le=1000, description="largest distance, per coordinate, of a measured "
                                   "position from where the robot was sent (nominal frames), mm; a pose farther off "
                                   "is measured again (a stale or wrong frame), never stored as good; 0: not checked")
    plausibility_deg: float = Field(0.1, ge=0, le=180, description="the same for the measured angles, degrees "
                                    "(the angle calibration checks the angle about the table's axis)")
    operator: str | None = Field(None, max_length=200, description="who runs the test, recorded in its conditions "
                                 "(default: $INSTRUMENT_OPERATOR, else the login name)")


class ProcedureBase(_Strict):
    """A procedure file. Each kind narrows ``procedure`` to its own name and ``parameters`` to its model."""

    procedure: str
    name: str | None = None
    description: str = ""
    hooks: list[HookSpec] = Field(default_factory=list)
    parameters: MotionParameters


MAX_RETRY_WAIT_S = 10.0


def retry_wait(params: MotionParameters, attempt: int) -> float:
    """Seconds to wait before retry number ``attempt + 1``: ``retry_backoff_s`` doubled at each
    retry, at most ``MAX_RETRY_WAIT_S`` (so a glitch of a few seconds is waited out, and a
    persistent fault fails a pose in bounded time)."""
    return float(min(params.retry_backoff_s * 2.0**attempt, MAX_RETRY_WAIT_S))
