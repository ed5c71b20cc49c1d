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
poses) and to the ground-truth log. In a cell whose twins run in separate processes, each process
holds a ``World`` attached to one shared state file (``World.share`` / ``World.attach``).
"""

from __future__ import annotations

import json
import os
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
from sim_devices._world_channel import StateRecord, WakeUps, WorldChannel

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


# A world whose OPR and tool are mounted exactly as the station says (a ``WorldConfig`` override).
EXACT_MOUNTS: dict[str, Any] = {"kinematics": {"opr_mount_translation_std": 0.0, "opr_mount_rotation_std": 0.0,
                                               "tool_translation_std": 0.0, "tool_rotation_std": 0.0}}


@dataclass
class WorldConfig:
    """``seed`` draws the cell's true constants (geometry, mounts, biases) and its noise; ``session``
    (0, 1, 2 …) draws the noise anew: a cell started again for the same run (a resume) has the same
    physics and fresh noise, as a real cell has. Session 0 is the noise of a cell that gives no session."""

    seed: int = 0
    kinematics: KinematicsConfig = field(default_factory=KinematicsConfig)
    session: int = 0
    ack_timeout_s: float = 10.0  # how long a settled change waits at most for the other processes' subscribers

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> WorldConfig:
        data = checked_fields(cls, data, "world config")
        kinematics = KinematicsConfig(
            **checked_fields(KinematicsConfig, data.get("kinematics"), "world config kinematics")
        )
        session = int(data.get("session", 0))
        if session < 0:
            raise ValueError(f"world config: session must be ≥ 0, got {session}")
        ack_timeout = float(data.get("ack_timeout_s", 10.0))
        if not ack_timeout > 0:
            raise ValueError(f"world config: ack_timeout_s must be > 0 s, got {ack_timeout}")
        return cls(seed=int(data.get("seed", 0)), kinematics=kinematics, session=session, ack_timeout_s=ack_timeout)


def session_seed(seed: int, session: int, stream: str) -> list[int]:
    """The seed sequence of noise ``stream`` in ``session`` of the cell seeded ``seed`` (session 0:
    ``[seed, crc32(stream)]``, as every stream was before sessions existed)."""
    base = [int(seed), zlib.crc32(stream.encode())]
    return base if session == 0 else [*base, int(session)]


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
    """Ground truth, one JSON object per line: every settled pose, every frame rendered, every payload.

    Each entry is appended with one ``write`` to a file opened ``O_APPEND``, so the twins of a cell,
    each in its own process, can share one log without interleaving lines. With ``shared=True``
    ``entries()`` reads the file (every process's entries); otherwise it returns this process's own.
    """

    def __init__(self, path: str | Path | None = None, keep_in_memory: int = 100_000, *, shared: bool = False) -> None:
        self.path = Path(path) if path else None
        self.shared = bool(shared and self.path)
        self._entries: list[dict[str, Any]] = []
        self._keep = keep_in_memory
        self._lock = threading.Lock()
        self._fd: int | None = None
        if self.path:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        self._read_offset = 0
        self._partial = b""

    def record(self, event: str, **data: Any) -> dict[str, Any]:
        entry = {"event": event, **{k: _jsonable(v) for k, v in data.items()}}
        line = (json.dumps(entry) + "\n").encode()
        with self._lock:
            if not self.shared:
                self._remember(entry)
            if self._fd is not None:
                os.write(self._fd, line)  # one write of a whole line: atomic among O_APPEND writers
        return entry

    def entries(self, event: str | None = None) -> list[dict[str, Any]]:
        with self._lock:
            if self.shared:
                self._follow_file()
            return [e for e in self._entries if event is None or e["event"] == event]

    def close(self) -> None:
        with self._lock:
            if self._fd is not None:
                os.close(self._fd)
                self._fd = None

    def _remember(self, entry: dict[str, Any]) -> None:
        self._entries.append(entry)
        if len(self._entries) > self._keep:
            del self._entries[: len(self._entries) - self._keep]

    def _follow_file(self) -> None:
        """Read the lines appended since the last call (any process's)."""
        assert self.path is not None
        try:
            with open(self.path, "rb") as handle:
                handle.seek(self._read_offset)
                chunk = handle.read()
        except FileNotFoundError:
            return
        self._read_offset += len(chunk)
        lines = (self._partial + chunk).split(b"\n")
        self._partial = lines.pop()  # an unfinished last line waits for its end
        for line in lines:
            if line.strip():
                try:
                    self._remember(json.loads(line))
                except ValueError:
                    continue  # a line cut short by a crash


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


class World:
    """The one shared truth. Thread-safe.

    In one process every twin holds the same instance. In a cell of processes every twin process
    holds its own ``World`` attached to one shared state file (``share`` in the supervisor,
    ``attach`` in the twins; see ``sim_devices._world_channel``): the constants (mountings, table
    axes) follow from the seed, the state (flange pose, mount, table angle, settled) lives in the
    file, and subscribers in every process see every change.

    Parameters
    ----------
    config : WorldConfig
        Seed and nominal/true spreads.
    clock : callable
        Returns seconds; ``time.time`` by default so truth lines up with host frame timestamps.
    truth_path : path, optional
        Where to append the ground-truth log (JSON lines).
    channel : WorldChannel, optional
        The shared state of a cell (``World.attach`` builds one); None: the state is this object's.
    ack_timeout : float, optional
        Seconds a settled change waits at most for the subscribers of other processes (default: the
        config's ``ack_timeout_s``).
    """

    def __init__(
        self,
        config: WorldConfig | None = None,
        clock: Callable[[], float] = time.time,
        truth_path: str | Path | None = None,
        *,
        channel: WorldChannel | None = None,
        ack_timeout: float | None = None,
    ) -> None:
        self.config = config or WorldConfig()
        self.clock = clock
        self.truth = TruthLog(truth_path, shared=channel is not None)
        self.ack_timeout = float(self.config.ack_timeout_s if ack_timeout is None else ack_timeout)
        self._lock = threading.RLock()
        self._subscribers: list[Callable[[WorldState], None]] = []
        self._announce_listeners: list[Callable[[WorldState], None]] = []
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
        self._m_to_base = invert(self.base_to_m)

        self._flange = self.reference_flange_pose.copy()
        self._mount = "robot"
        self._table_angle = 0.0
        self._settled = True
        self._last_settled = 0

        # Shared mode: the state lives in the channel; a watcher thread serves this process's
        # subscribers when another process changes it.
        self._channel = channel
        self._delivered = -1
        self._delivered_settled = -1
        self._deliver_lock = threading.RLock()
        self._slot: int | None = None
        self._watcher: threading.Thread | None = None
        self._watcher_stop = threading.Event()
        if channel is not None:
            self._delivered = self._delivered_settled = channel.read().seq

    # ----------------------------------------------------------------------------- shared mode
    @classmethod
    def attach(cls, directory: str | Path, config: WorldConfig | None = None, truth_path: str | Path | None = None,
               clock: Callable[[], float] = time.time) -> World:
        """This process's view of a cell's shared world (created by ``share`` in ``directory``)."""
        return cls(config, clock, truth_path, channel=WorldChannel.attach(directory))

    def share(self, directory: str | Path) -> Path:
        """Move this world's state into a new shared state file in ``directory`` (the cell supervisor,
        before it starts the twins' processes); returns the directory to ``attach`` to."""
        with self._lock:
            if self._channel is not None:
                raise RuntimeError("world: already shared")
            self._channel = WorldChannel.create(directory, flange=self._flange, mount=self._mount,
                                                table_angle=self._table_angle, settled=self._settled,
                                                time_now=self.clock())
            self.truth.shared = self.truth.path is not None
            self._delivered = self._delivered_settled = 0
            if self._subscribers or self._announce_listeners:
                self._start_watcher()
        return Path(directory)

    @property
    def channel(self) -> WorldChannel | None:
        return self._channel

    def close(self) -> None:
        """Stop serving subscribers, leave the shared state, close the ground-truth log."""
        self._stop_watcher()
        if self._channel is not None:
            self._channel.close()
        self.truth.close()

    # ----------------------------------------------------------------------------- randomness
    def rng(self, stream: str) -> np.random.Generator:
        """An independent, reproducible random stream per subsystem name: the cell's constants (the
        same in every session)."""
        return np.random.default_rng([self.config.seed, zlib.crc32(stream.encode())])

    def noise_rng(self, stream: str) -> np.random.Generator:
        """The random stream of a noise process (``session_seed(seed, session, stream)``): drawn anew
        in every session of the cell, the same as ``rng(stream)`` in session 0."""
        return np.random.default_rng(session_seed(self.config.seed, self.config.session, stream))

    # ----------------------------------------------------------------------------- setters
    def set_flange_pose(self, flange_pose: np.ndarray, *, settled: bool = True, source: str = "robot") -> WorldState:
        """Set the true flange pose ``T_B_F`` (4×4, or a UR pose (6,)).

        Returns once every subscriber has seen the new state; for a settled state that includes
        the subscribers of the cell's other processes (the camera renderer), at most
        ``ack_timeout`` seconds.
        """
        return self._update(source, flange=_matrix(flange_pose), settled=settled)

    def mount_on_robot(self) -> WorldState:
        return self._update("mount", mount="robot")

    def mount_on_table(self, axis: Axis) -> WorldState:
        if axis not in AXES:
            raise ValueError(f"table axis must be one of 'x', 'y', 'z', got {axis!r}")
        return self._update("mount", mount=f"table:{axis}")

    def set_table_angle(self, angle: float, *, settled: bool = True) -> WorldState:
        return self._update("table", table_angle=float(angle), settled=settled)

    def announce(self, *, flange_pose: np.ndarray | None = None, table_angle: float | None = None) -> None:
        """Say what is expected to settle next (a hint, not truth): a robot that has planned a move
        announces its final attained flange pose, so the camera twin can render it ahead of time."""
        flange = None if flange_pose is None else _matrix(flange_pose)
        if self._channel is not None:
            self._channel.write_hint(flange=flange, table_angle=table_angle)
            self._channel.wake_others()
            return
        expected = self._expected_state(flange, table_angle)
        for callback in list(self._announce_listeners):
            callback(expected)

    # ----------------------------------------------------------------------------- readers
    @property
    def mount(self) -> str:
        return self._record().mount

    def flange_pose(self) -> np.ndarray:
        return self._record().flange.copy()

    def table_angle(self) -> float:
        return self._record().table_angle

    def opr_in_m(self) -> np.ndarray:
        """True pose of the OPR in M, ``T_M_O``."""
        record = self._record()
        return self._opr_in_m(record.mount, record.flange, record.table_angle)

    def tool_in_m(self) -> np.ndarray:
        """True pose of the end-effector measuring point in M, ``T_M_E``."""
        return self._m_to_base @ self._record().flange @ self.true_tool

    def state(self) -> WorldState:
        record = self._record()
        return self._state_of(record, self.clock())

    # ----------------------------------------------------------------------------- subscribers
    def subscribe(self, callback: Callable[[WorldState], None]) -> None:
        """``callback(state)`` on every change.

        A change made in this process calls it synchronously, under the world's lock; a change
        made by another process of the cell calls it on this process's watcher thread (when
        several changes came at once: the latest settled one among them, with its own data, then the
        latest). Either way a settled change is only complete once every callback has returned.
        """
        with self._lock:
            self._subscribers.append(callback)
            if self._channel is not None:
                self._start_watcher()

    def unsubscribe(self, callback: Callable[[WorldState], None]) -> None:
        with self._lock:
            if callback in self._subscribers:
                self._subscribers.remove(callback)
            if not self._subscribers and not self._announce_listeners:
                self._stop_watcher()

    def on_announce(self, callback: Callable[[WorldState], None]) -> None:
        """``callback(expected)`` for every ``announce`` (in any process): the state expected next."""
        with self._lock:
            self._announce_listeners.append(callback)
            if self._channel is not None:
                self._start_watcher()

    def remove_announce_listener(self, callback: Callable[[WorldState], None]) -> None:
        with self._lock:
            if callback in self._announce_listeners:
                self._announce_listeners.remove(callback)
            if not self._subscribers and not self._announce_listeners:
                self._stop_watcher()

    # ----------------------------------------------------------------------------- internals
    def _record(self) -> StateRecord:
        if self._channel is not None:
            return self._channel.read()
        with self._lock:
            return StateRecord(self._seq, self.clock(), self._settled, self._mount, self._flange.copy(),
                               self._table_angle, self._last_settled)

    def _opr_in_m(self, mount: str, flange: np.ndarray, table_angle: float) -> np.ndarray:
        if mount == "robot":
            return self._m_to_base @ flange @ self.true_opr_mount
        axis = self.true_table_axes[mount.split(":")[1]]
        return make_transform(rotvec_to_matrix(axis * table_angle))

    def _state_of(self, record: StateRecord, when: float | None = None) -> WorldState:
        return WorldState(
            seq=record.seq,
            time=record.time if when is None else when,
            settled=record.settled,
            mount=record.mount,
            flange_pose=record.flange.copy(),
            table_angle=record.table_angle,
            opr_in_m=self._opr_in_m(record.mount, record.flange, record.table_angle),
            tool_in_m=self._m_to_base @ record.flange @ self.true_tool,
        )

    def _expected_state(self, flange: np.ndarray | None, table_angle: float | None) -> WorldState:
        record = self._record()
        flange = record.flange if flange is None else flange
        angle = record.table_angle if table_angle is None else float(table_angle)
        return self._state_of(StateRecord(record.seq, self.clock(), True, record.mount, flange, angle,
                                          record.last_settled))

    def _update(self, source: str, *, flange: np.ndarray | None = None, mount: str | None = None,
                table_angle: float | None = None, settled: bool | None = None) -> WorldState:
        channel = self._channel
        if channel is None:
            with self._lock:
                if flange is not None:
                    self._flange = flange.copy()
                if mount is not None:
                    self._mount = mount
                if table_angle is not None:
                    self._table_angle = table_angle
                if settled is not None:
                    self._settled = settled
                self._seq += 1
                if self._settled:
                    self._last_settled = self._seq
                state = self._state_of(self._record(), self.clock())
                self._log(state, source)
                for callback in list(self._subscribers):
                    callback(state)
                return state
        with self._lock:  # one publisher of this process at a time keeps local delivery in order
            record = channel.write(flange=flange, mount=mount, table_angle=table_angle, settled=settled,
                                   time_now=self.clock())
            state = self._state_of(record)
            self._log(state, source)
            self._deliver(record)
            channel.wake_others()
        if state.settled:
            late = channel.wait_for_acks(state.seq, self.ack_timeout)
            if late:
                self.truth.record("late_subscribers", seq=state.seq, time=self.clock(), pids=late,
                                  waited=self.ack_timeout)
        return state

    def _log(self, state: WorldState, source: str) -> None:
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

    def _deliver(self, record: StateRecord) -> None:
        """Run this process's subscribers once per new state (shared mode), then acknowledge it.

        The invariant the robot's "done" rests on: this process acknowledges a settled seq only after
        its subscribers have been called with THAT settled state's data. A settled state overtaken by
        newer (moving) ones before this process got to it is delivered first, from the channel's
        settled slot: the pose the robot was passing through afterwards is not what it settled at.
        """
        with self._deliver_lock:
            if (self._channel is not None and record.last_settled > self._delivered_settled
                    and record.last_settled != record.seq):
                self._call_subscribers(self._channel.read_settled())  # its seq >= record.last_settled
            self._call_subscribers(record)
            if self._slot is not None and self._channel is not None:
                self._channel.ack(self._slot, self._delivered)

    def _call_subscribers(self, record: StateRecord) -> None:
        if record.seq <= self._delivered:
            return  # delivered already (or older than what was)
        self._delivered = record.seq
        if record.settled:
            self._delivered_settled = record.seq
        state = self._state_of(record)
        for callback in list(self._subscribers):
            callback(state)

    def _start_watcher(self) -> None:
        if self._watcher is not None or self._channel is None:
            return
        channel = self._channel
        self._slot = channel.claim_slot()
        wake_ups = WakeUps(channel.wake_path(self._slot))
        self._watcher_stop.clear()
        self._watcher = threading.Thread(target=self._watch, args=(channel, wake_ups), name="world-watcher",
                                         daemon=True)
        self._watcher.start()

    def _stop_watcher(self) -> None:
        watcher, self._watcher = self._watcher, None
        if watcher is None:
            return
        self._watcher_stop.set()
        if watcher is not threading.current_thread():
            watcher.join(5.0)
        if self._slot is not None and self._channel is not None and not self._channel.closed:
            self._channel.release_slot(self._slot)
        self._slot = None

    def _watch(self, channel: WorldChannel, wake_ups: WakeUps) -> None:
        last_hint = channel.read_hint().id
        try:
            while not self._watcher_stop.is_set():
                wake_ups.wait(0.2)  # woken by a publisher; the timeout only guards against a lost wake-up
                if self._watcher_stop.is_set():
                    break
                hint = channel.read_hint()
                if hint.id != last_hint:
                    last_hint = hint.id
                    expected = self._expected_state(hint.flange, hint.table_angle)
                    for callback in list(self._announce_listeners):
                        callback(expected)
                self._deliver(channel.read())
        finally:
            wake_ups.close()

    def describe(self) -> dict[str, Any]:
        """Nominal and true constants, for the ground-truth log and for tests."""
        return {
            "seed": self.config.seed,
            "session": self.config.session,
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


def _matrix(pose: np.ndarray) -> np.ndarray:
    pose = np.asarray(pose, dtype=float)
    return pose6_to_matrix(pose) if pose.shape == (6,) else pose.copy()


def _tilted_axis(index: int, rng: np.random.Generator, std: float) -> np.ndarray:
    axis = np.zeros(3)
    axis[index] = 1.0
    axis += rng.normal(0.0, std, 3) * (np.arange(3) != index)
    return axis / np.linalg.norm(axis)
