"""The ISO 9283 pose test's parameters, its procedure file and the cube's points in the cycle's order.

Below the kind, its analysis and its test conditions, which all read them: the plan and the test
conditions share ``cube_path``, so the commanded poses a run reports are the ones it planned.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from instrument.iso9283 import iso_cube_points
from procedures.kinds._parameters import MotionParameters, ProcedureBase
from procedures.station import StationFile, Vec3, translated_in_frame


def _paper_cube_center() -> list[float]:
    return [0.035, 0.035, 0.035]


def _no_offset() -> list[float]:
    return [0.0, 0.0, 0.0]


class IsoParameters(MotionParameters):
    cube_center_m: Vec3 = Field(default_factory=_paper_cube_center, description="cube centre in M, metres")
    cube_edge_m: float = Field(0.07, gt=0, le=2.0, description="cube edge, metres")
    cycles: int = Field(30, ge=2, le=10000, description="ISO 9283 cycles (the standard asks for 30)")
    transform_step: bool = Field(True, description="measure the cube once first and fit the robot↔M transform")
    apply_compensation: bool = Field(True, description="correct poses with the calibration record in force")
    payload_mass_kg: float | None = Field(
        None, ge=0, le=2000, description="payload mass, kg: set on the robot before the cycles and recorded (ISO 9283 "
        "tests at the rated payload); null: not set, recorded as not stated")
    payload_cog_m: Vec3 = Field(default_factory=_no_offset, description="payload centre of gravity in the tool "
                                "flange frame, metres")
    warm_up: Literal["declared", "run"] = Field(
        "declared", description="declared: the robot warmed up for warm_up_s before the run (recorded); run: the "
        "procedure cycles the robot over the cube's points for warm_up_s before the first measured pose")
    warm_up_s: float = Field(0.0, ge=0, le=86400, description="warm-up time, s")
    record_environment: bool = Field(True, description="read the interferometer's environmental unit at every "
                                     "pose when the station has an interferometer (the test's air and drift)")
    uncertainty_draws: int = Field(1000, ge=0, le=100000, description="Monte Carlo draws of the measurement "
                                   "uncertainty (0: not evaluated)")
    drift_cycles: int | None = Field(None, ge=2, le=5000, description="cycles at the start and at the end "
                                     "compared for the drift figures (default: a third of the cycles)")
    frame_squareness_urad: float | None = Field(
        None, ge=0, le=100000, description="standard uncertainty of the instrument's position frame against its "
        "angle frame (squareness and rotation), µrad: neither calibration measures it; stated here it enters the "
        "uncertainty of AP and AD, null leaves it out (and the results say so)")


class Iso9283Repeatability(ProcedureBase):
    procedure: Literal["iso9283_repeatability"]
    parameters: IsoParameters = Field(default_factory=IsoParameters)


def cube_path(params: IsoParameters, station: StationFile) -> list[tuple[str, list[float], list[float]]]:
    """(label, position in M, commanded TCP pose in the base frame) of P1…P5 in the cycle's order."""
    cube = iso_cube_points(np.asarray(params.cube_center_m, dtype=float), float(params.cube_edge_m))
    reference = station.frames.reference_tcp_pose
    return [(label, [float(v) for v in point], translated_in_frame(reference, point).tolist())
            for label, point in zip(cube.order, cube.positions_in_order())]
