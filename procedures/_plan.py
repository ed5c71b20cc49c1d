"""What a procedure does, as a fixed list of steps.

A run's plan is a pure function of the procedure parameters and the station, so a resumed run
rebuilds exactly the same list and skips the steps whose samples are already committed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from procedures._geometry import translated_in_frame
from procedures._models import (
    AngleCalibration,
    DisplacementCalibration,
    Iso9283Repeatability,
    ProcedureFile,
    StationFile,
)

AXIS_INDEX = {"x": 0, "y": 1, "z": 2}


@dataclass(frozen=True)
class Step:
    """One measured pose.

    Attributes
    ----------
    index : int
        Position in the plan (0-based); the sample's key in the store.
    key : str
        Readable identity, e.g. ``"disp/x/g1/r0/p03"``.
    phase : str
        ``"calibration"``, ``"transform"`` or ``"iso"``.
    setup : str
        What must be true of the cell: ``"robot"`` (OPR on the flange), ``"align:x"`` (OPR on the
        robot and interferometer aligned to axis x) or ``"table:x"`` (OPR on the table for axis x).
    tcp_pose : (6,) list or None
        Commanded UR TCP pose in the base frame (metres, rotation vector).
    table_angle : float or None
        Commanded table angle, rad.
    label : str
        Point name (``"P1"``) or calibration point.
    meta : dict
        Axis, group, repeat, cycle, nominal value (SI) ...
    """

    index: int
    key: str
    phase: str
    setup: str
    tcp_pose: list[float] | None = None
    table_angle: float | None = None
    label: str = ""
    meta: dict[str, Any] = field(default_factory=dict)


def _inclusive_range(start: float, stop: float, step: float) -> np.ndarray:
    count = int(np.floor((stop - start) / step + 1e-9)) + 1
    return start + step * np.arange(count)


def displacement_plan(proc: DisplacementCalibration, station: StationFile) -> list[Step]:
    p = proc.parameters
    values = _inclusive_range(p.start_mm, p.stop_mm, p.step_mm) * 1e-3
    steps: list[Step] = []
    for axis in p.axes:
        k = AXIS_INDEX[axis]
        for g, offset_mm in enumerate(p.group_start_offsets_mm):
            offset = np.asarray(offset_mm) * 1e-3
            for r in range(p.repeats):
                for i, value in enumerate(values):
                    position = offset.copy()
                    position[k] += value
                    steps.append(Step(
                        index=len(steps), key=f"disp/{axis}/g{g}/r{r}/p{i:02d}", phase="calibration",
                        setup=f"align:{axis}",
                        tcp_pose=translated_in_frame(station.frames.reference_tcp_pose, position).tolist(),
                        label=f"{axis}={value * 1e3:g} mm",
                        meta={"axis": axis, "group": g, "repeat": r, "point": i, "nominal": float(position[k]),
                              "group_start": float(offset[k] + values[0]),
                              "zero_interferometer": r == 0 and i == 0},
                    ))
    return steps


def angle_plan(proc: AngleCalibration, station: StationFile) -> list[Step]:
    p = proc.parameters
    values = np.radians(_inclusive_range(p.start_deg, p.stop_deg, p.step_deg))
    steps: list[Step] = []
    for axis in p.axes:
        for g, offset_deg in enumerate(p.group_start_offsets_deg):
            for r in range(p.repeats):
                for i, value in enumerate(values):
                    angle = float(value + np.radians(offset_deg))
                    steps.append(Step(
                        index=len(steps), key=f"angle/{axis}/g{g}/r{r}/p{i:02d}", phase="calibration",
                        setup=f"table:{axis}", table_angle=angle, label=f"{axis}={np.degrees(angle):.4g}°",
                        meta={"axis": axis, "group": g, "repeat": r, "point": i, "nominal": angle},
                    ))
    return steps


def iso_plan(proc: Iso9283Repeatability, station: StationFile,
             cube_points: Callable[[np.ndarray, float], tuple[list[str], np.ndarray]]) -> list[Step]:
    """The transform pass (optional) then ``cycles`` passes over the cube in the paper's order.

    ``cube_points(center, edge)`` gives the point labels in visiting order and their positions in M.
    """
    p = proc.parameters
    labels, points = cube_points(np.asarray(p.cube_center_m, dtype=float), float(p.cube_edge_m))
    reference = station.frames.reference_tcp_pose
    steps: list[Step] = []

    def add(phase: str, cycle: int, label: str, point: np.ndarray) -> None:
        steps.append(Step(
            index=len(steps), key=f"{phase}/c{cycle:03d}/{label}", phase=phase, setup="robot",
            tcp_pose=translated_in_frame(reference, point).tolist(), label=label,
            meta={"cycle": cycle, "point": label, "position_in_m": [float(v) for v in point]},
        ))

    if p.transform_step:
        for label, point in zip(labels, points):
            add("transform", 0, label, point)
    for cycle in range(p.cycles):
        for label, point in zip(labels, points):
            add("iso", cycle, label, point)
    return steps


def build_plan(proc: ProcedureFile, station: StationFile, science) -> list[Step]:
    if isinstance(proc, DisplacementCalibration):
        return displacement_plan(proc, station)
    if isinstance(proc, AngleCalibration):
        return angle_plan(proc, station)
    if isinstance(proc, Iso9283Repeatability):
        return iso_plan(proc, station, science.cube_points)
    raise TypeError(f"no plan for {type(proc).__name__}")
