"""The simulated world: one seeded object that holds the physical truth every twin shares.

Frames
------
- **B**, the robot base. The robot twin sets the true flange pose ``T_B_F`` in it.
- **F**, the flange. The OPR is bolted to it by the true mounting ``T_F_O`` (the station file only
  knows the nominal mounting; the two differ by a fraction of a millimetre and a few hundredths of
  a degree).
- **O**, the optical pose reference (OPR): its X, Y, Z beams are the axes of O.
- **M**, the measurement frame: by definition the OPR frame when the robot stands at the reference
  flange pose, ``T_B_M = T_B_Fref @ T_F_O``. The sensor module's screens are placed in M.
- **E**, the end effector's measuring point (the ISO 9283 point), ``T_F_E`` true and nominal.

During angle calibration the OPR is taken off the robot and put on the rotary table, whose axis
is (nearly) one of M's axes through M's origin; then the table angle, not the robot, poses it.

Every change of the true pose goes to the subscribers (the camera renderer renders on settled
poses) and to the ground-truth log.
"""

from __future__ import annotations

import json
import threading
import time
import zlib
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from sim_devices._config import checked_fields
from sim_devices._transforms import (
    invert,
    make_transform,
    matrix_to_euler,
    matrix_to_pose6,
    pose6_to_matrix,
    rotvec_to_matrix,
    small_random_transform,
)

Axis = Literal["x", "y", "z"]
AXES: dict[str, int] = {"x": 0, "y": 1, "z": 2}


@dataclass
class KinematicsConfig:
    """Nominal values (what a station file claims) and the spread of the true ones around them."""

    reference_flange_pose: list[float] = field(
        default_factory=lambda: [0.45, -0.10, 0.35, np.pi, 0.0, 0.0]
    )  # UR pose in B
    opr_mount_nominal: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.08, 0.0, 0.0, 0.0])  # in F
    opr_mount_translation_std: float = 0.3e-3
    opr_mount_rotation_std: float = float(np.radians(0.05))
    tool_nominal: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.15, 0.0, 0.0, 0.0])  # E in F
    tool_translation_std: float = 0.2e-3
    tool_rotation_std: float = float(np.radians(0.03))
    table_axis_misalignment_std: float = float(np.radians(0.005))


@dataclass
class WorldConfig:
    seed: int = 0
    kinematics: KinematicsConfig = field(default_factory=KinematicsConfig)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> WorldConfig:
        data = checked_fields(cls, data, "world config")
        kinematics = KinematicsConfig(
            **checked_fields(KinematicsConfig, data.get("kinematics"), "world config kinematics")
        )
        return cls(seed=int(data.get("seed", 0)), kinematics=kinematics)


@dataclass(frozen=True)
class WorldState:
    """A consistent snapshot of the truth, handed to subscribers."""

    seq: int
    time: float
    settled: bool
    mount: str  # "robot" or "table:x" / "table:y" / "table:z"
    flange_pose: np.ndarray  # T_B_F, 4×4
    table_angle: float  # rad, true
    opr_in_m: np.ndarray  # T_M_O, 4×4
    tool_in_m: np.ndarray  # T_M_E, 4×4 (robot mount only; identity-composed otherwise)


class TruthLog:
    """Ground truth, one JSON object per line: every settled pose and every frame rendered."""

    def __init__(self, path: str | Path | None = None, keep_in_memory: int = 100_000) -> None:
        self.path = Path(path) if path else None
        self._entries: list[dict[str, Any]] = []
        self._keep = keep_in_memory
        self._lock = threading.Lock()
        self._file = open(self.path, "a", buffering=1, encoding="utf-8") if self.path else None

    def record(self, event: str, **data: Any) -> dict[str, Any]:
        entry = {"event": event, **{k: _jsonable(v) for k, v in data.items()}}
        with self._lock:
            self._entries.append(entry)
            if len(self._entries) > self._keep:
                del self._entries[: len(self._entries) - self._keep]
            if self._file:
                self._file.write(json.dumps(entry) + "\n")
        return entry

    def entries(self, event: str | None = None) -> list[dict[str, Any]]:
        with self._lock:
            return [e for e in self._entries if event is None or e["event"] == event]

    def close(self) -> None:
        with self._lock:
            if self._file:
                self._file.close()
                self._file = None


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


class World:
    """The one shared truth. Thread-safe; every twin of a cell holds the same instance.

    Parameters
    ----------
    config : WorldConfig
        Seed and nominal/true spreads.
    clock : callable
        Returns seconds; ``time.time`` by default so truth lines up with host frame timestamps.
    truth_path : path, optional
        Where to append the ground-truth log (JSON lines).
    """

    def __init__(
        self,
        config: WorldConfig | None = None,
        clock: Callable[[], float] = time.time,
        truth_path: str | Path | None = None,
    ) -> None:
        self.config = config or WorldConfig()
        self.clock = clock
        self.truth = TruthLog(truth_path)
        self._lock = threading.RLock()
        self._subscribers: list[Callable[[WorldState], None]] = []
        self._seq = 0

        kin = self.config.kinematics
        rng = self.rng("kinematics")
        self.reference_flange_pose = pose6_to_matrix(kin.reference_flange_pose)
        self.nominal_opr_mount = pose6_to_matrix(kin.opr_mount_nominal)
        self.true_opr_mount = self.nominal_opr_mount @ small_random_transform(
            rng, kin.opr_mount_translation_std, kin.opr_mount_rotation_std
        )
        self.nominal_tool = pose6_to_matrix(kin.tool_nominal)
        self.true_tool = self.nominal_tool @ small_random_transform(
            rng, kin.tool_translation_std, kin.tool_rotation_std
        )
        self.true_table_axes = {
            name: _tilted_axis(index, rng, kin.table_axis_misalignment_std) for name, index in AXES.items()
        }
        # M is, by definition, the true OPR frame at the reference pose.
        self.base_to_m = self.reference_flange_pose @ self.true_opr_mount
        self.nominal_base_to_m = self.reference_flange_pose @ self.nominal_opr_mount

        self._flange = self.reference_flange_pose.copy()
        self._mount = "robot"
        self._table_angle = 0.0
        self._settled = True

    # ----------------------------------------------------------------------------- randomness
    def rng(self, stream: str) -> np.random.Generator:
        """An independent, reproducible random stream per subsystem name."""
        return np.random.default_rng([self.config.seed, zlib.crc32(stream.encode())])

    # ----------------------------------------------------------------------------- setters
    def set_flange_pose(self, flange_pose: np.ndarray, *, settled: bool = True, source: str = "robot") -> WorldState:
        """Set the true flange pose ``T_B_F`` (4×4, or a UR pose (6,))."""
        pose = np.asarray(flange_pose, dtype=float)
        pose = pose6_to_matrix(pose) if pose.shape == (6,) else pose
        with self._lock:
            self._flange = pose.copy()
            self._settled = settled
            return self._publish(source)

    def mount_on_robot(self) -> WorldState:
        with self._lock:
            self._mount = "robot"
            return self._publish("mount")

    def mount_on_table(self, axis: Axis) -> WorldState:
        if axis not in AXES:
            raise ValueError(f"table axis must be one of 'x', 'y', 'z', got {axis!r}")
        with self._lock:
            self._mount = f"table:{axis}"
            return self._publish("mount")

    def set_table_angle(self, angle: float, *, settled: bool = True) -> WorldState:
        with self._lock:
            self._table_angle = float(angle)
            self._settled = settled
            return self._publish("table")

    # ----------------------------------------------------------------------------- readers
    @property
    def mount(self) -> str:
        return self._mount

    def flange_pose(self) -> np.ndarray:
        with self._lock:
            return self._flange.copy()

    def table_angle(self) -> float:
        return self._table_angle

    def opr_in_m(self) -> np.ndarray:
        """True pose of the OPR in M, ``T_M_O``."""
        with self._lock:
            return self._opr_in_m_locked()

    def tool_in_m(self) -> np.ndarray:
        """True pose of the end-effector measuring point in M, ``T_M_E``."""
        with self._lock:
            return invert(self.base_to_m) @ self._flange @ self.true_tool

    def state(self) -> WorldState:
        with self._lock:
            return self._snapshot()

    # ----------------------------------------------------------------------------- subscribers
    def subscribe(self, callback: Callable[[WorldState], None]) -> None:
        """``callback(state)`` runs synchronously, under the world's lock, on every change: a twin
        that reports "move done" after ``set_flange_pose`` returns knows every subscriber (the
        renderer) has seen the pose."""
        with self._lock:
            self._subscribers.append(callback)

    def unsubscribe(self, callback: Callable[[WorldState], None]) -> None:
        with self._lock:
            if callback in self._subscribers:
                self._subscribers.remove(callback)

    # ----------------------------------------------------------------------------- internals
    def _opr_in_m_locked(self) -> np.ndarray:
        if self._mount == "robot":
            return invert(self.base_to_m) @ self._flange @ self.true_opr_mount
        axis = self.true_table_axes[self._mount.split(":")[1]]
        return make_transform(rotvec_to_matrix(axis * self._table_angle))

    def _snapshot(self) -> WorldState:
        return WorldState(
            seq=self._seq,
            time=self.clock(),
            settled=self._settled,
            mount=self._mount,
            flange_pose=self._flange.copy(),
            table_angle=self._table_angle,
            opr_in_m=self._opr_in_m_locked(),
            tool_in_m=invert(self.base_to_m) @ self._flange @ self.true_tool,
        )

    def _publish(self, source: str) -> WorldState:
        self._seq += 1
        state = self._snapshot()
        if state.settled:
            self.truth.record(
                "pose",
                seq=state.seq,
                time=state.time,
                source=source,
                mount=state.mount,
                flange_pose=matrix_to_pose6(state.flange_pose),
                table_angle=state.table_angle,
                opr_in_m=pose_record(state.opr_in_m),
                tool_in_m=pose_record(state.tool_in_m),
            )
        for callback in list(self._subscribers):
            callback(state)
        return state

    def describe(self) -> dict[str, Any]:
        """Nominal and true constants, for the ground-truth log and for tests."""
        return {
            "seed": self.config.seed,
            "kinematics": asdict(self.config.kinematics),
            "true_opr_mount": matrix_to_pose6(self.true_opr_mount).tolist(),
            "nominal_opr_mount": matrix_to_pose6(self.nominal_opr_mount).tolist(),
            "true_tool": matrix_to_pose6(self.true_tool).tolist(),
            "nominal_tool": matrix_to_pose6(self.nominal_tool).tolist(),
            "base_to_m": matrix_to_pose6(self.base_to_m).tolist(),
            "nominal_base_to_m": matrix_to_pose6(self.nominal_base_to_m).tolist(),
            "true_table_axes": {k: v.tolist() for k, v in self.true_table_axes.items()},
        }


def pose_record(transform: np.ndarray) -> dict[str, list[float]]:
    """Translation (m) and Euler angles (alpha, theta, gamma; rad, R = Rz Ry Rx) of a 4×4."""
    return {"t": transform[:3, 3].tolist(), "euler": matrix_to_euler(transform[:3, :3]).tolist()}


def _tilted_axis(index: int, rng: np.random.Generator, std: float) -> np.ndarray:
    axis = np.zeros(3)
    axis[index] = 1.0
    axis += rng.normal(0.0, std, 3) * (np.arange(3) != index)
    return axis / np.linalg.norm(axis)
