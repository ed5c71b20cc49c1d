"""What every procedure file shares: its frame (kind, name, hooks) and the motion parameters.

Units are in the field names; the few operator-friendly fields in mm or degrees are converted
to SI by each kind when it builds its plan.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from procedures._models import HookSpec

AxisName = Literal["x", "y", "z"]


def all_axes() -> list[AxisName]:
    """The default axes of a calibration: every axis of M."""
    return ["x", "y", "z"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class MotionParameters(_Strict):
    """Parameters every kind has: how the robot moves, how a pose is measured, what failure is tolerated."""

    speed_percent: float = Field(50.0, gt=0, le=100, description="robot linear speed, % of the envelope's max_speed")
    acceleration_percent: float = Field(50.0, gt=0, le=100, description="% of the envelope's max_acceleration")
    settle_time_s: float = Field(0.5, ge=0, le=60, description="wait after a move before measuring, s")
    move_timeout_s: float = Field(60.0, gt=0, le=600, description="longest allowed move, s")
    frames_per_pose: int = Field(3, ge=1, le=100, description="camera frame triples averaged per pose")
    grab_timeout_s: float = Field(5.0, gt=0, le=120, description="per frame, s")
    retries_per_pose: int = Field(2, ge=0, le=10, description="re-measurements of a pose whose frames fail")
    max_failed_samples: int = Field(3, ge=0, description="failed poses tolerated before the run fails")
    save_frames: Literal["never", "failed", "always"] = Field("failed", description="which raw frames to keep")


class ProcedureBase(_Strict):
    """A procedure file. Each kind narrows ``procedure`` to its own name and ``parameters`` to its model."""

    procedure: str
    name: str | None = None
    description: str = ""
    hooks: list[HookSpec] = Field(default_factory=list)
    parameters: MotionParameters
