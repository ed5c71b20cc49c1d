"""Frame triples → a stream of timestamped poses (docs/dynamic.md, "Pose stream").

:class:`PoseStreamer` takes the three crosses of each trigger (:class:`FrameTriple`) and returns
a :class:`PoseSample` — or a :class:`Drop` naming why that trigger gave no pose. Nothing is ever
interpolated: a trigger that was not received, came out of order, lacks a cross, has frames whose
timestamps disagree, or whose crosses do not solve, is counted as dropped and leaves a gap in the
stream's ``index`` column. :class:`PoseTracker` does the same from images, following each cross
from frame to frame (``locate_cross(..., prior=last)``).

Per sample: the time on the robot controller's clock (the mean of the three cameras' timestamps,
each through its clock model), the pose as solved (``raw``, the OPR in M) and after the caller's
compensation and tool transform (``pose``), and quality figures.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from instrument._conventions import SCREENS
from instrument.pose import DEFAULT_MAX_RESIDUAL_RMS, Geometry, Pose, PoseError, solve_pose, tool_pose
from instrument.stream._clock import ClockModel
from instrument.vision import CrossMeasurement, CrossNotFound, VisionWorkspace, locate_crosses

DEFAULT_MAX_TIMESTAMP_SPREAD = 1e-3  # s: three frames of one trigger are stamped within this


@dataclass(frozen=True)
class FrameTriple:
    """The three crosses of one trigger.

    Attributes
    ----------
    index : int
        Trigger number; consecutive triggers have consecutive numbers (a gap = triggers lost).
    timestamps : mapping "x"/"y"/"z" → float
        Each camera's timestamp of its frame, s, on that camera's clock (the image's mean time:
        exposure start + half the exposure).
    crosses : mapping "x"/"y"/"z" → CrossMeasurement or None
        None where the vision found no cross.
    failures : mapping "x"/"y"/"z" → str
        Why a cross is missing (the vision's error), for the drop's reason.
    """

    index: int
    timestamps: Mapping[str, float]
    crosses: Mapping[str, CrossMeasurement | None]
    failures: Mapping[str, str] | None = None


@dataclass(frozen=True)
class PoseSample:
    """One streamed pose.

    Attributes
    ----------
    index : int
        Trigger number.
    time : float
        s, robot controller clock.
    pose : (6,) array
        [x, y, z, a, b, c] (m, rad) after compensation and the tool transform (if given).
    raw : (6,) array
        The OPR pose in M as solved, before compensation.
    residual_rms : float
        m, the solver's consistency figure (how well the six stripes agree on one rigid pose).
    timestamp_spread : float
        s, largest − smallest of the three frames' robot-clock times.
    min_sections : int
        Fewest cross-sections behind any of the six stripe lines.
    max_line_rms : float
        px, largest residual RMS of the six stripe line fits.
    tracked : int
        How many of the three crosses were found by tracking (0 when the triple came as crosses
        measured without a prior).
    """

    index: int
    time: float
    pose: np.ndarray
    raw: np.ndarray
    residual_rms: float
    timestamp_spread: float
    min_sections: int
    max_line_rms: float
    tracked: int


@dataclass(frozen=True)
class Drop:
    """Triggers that gave no pose: ``count`` consecutive ones from ``index``, and why."""

    index: int
    count: int
    reason: str


_COLUMNS = ("index", "time", "pose", "raw", "residual_rms", "timestamp_spread", "min_sections", "max_line_rms",
            "tracked")


@dataclass(frozen=True)
class PoseStream:
    """The stream as columns (one row per sample, in trigger order) and the drops.

    ``index`` (N,) int, ``time`` (N,) s robot clock, ``pose`` and ``raw`` (N, 6), ``residual_rms``
    (N,) m, ``timestamp_spread`` (N,) s, ``min_sections`` (N,) int, ``max_line_rms`` (N,) px,
    ``tracked`` (N,) int; ``drops`` the :class:`Drop` records.
    """

    index: np.ndarray
    time: np.ndarray
    pose: np.ndarray
    raw: np.ndarray
    residual_rms: np.ndarray
    timestamp_spread: np.ndarray
    min_sections: np.ndarray
    max_line_rms: np.ndarray
    tracked: np.ndarray
    drops: tuple[Drop, ...]

    def __len__(self) -> int:
        return len(self.index)

    @property
    def dropped(self) -> int:
        """Triggers that gave no pose (not received, or received and refused)."""
        return sum(d.count for d in self.drops)

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) m, the ``pose`` columns x, y, z (ready for ``instrument.iso9283``)."""
        return self.pose[:, :3]

    def sample(self, i: int) -> PoseSample:
        return PoseSample(*(getattr(self, name)[i] for name in _COLUMNS))


def _empty_stream(drops: tuple[Drop, ...]) -> PoseStream:
    return PoseStream(
        np.empty(0, np.int64), np.empty(0), np.empty((0, 6)), np.empty((0, 6)), np.empty(0), np.empty(0),
        np.empty(0, np.int64), np.empty(0), np.empty(0, np.int64), drops,
    )


class PoseStreamer:
    """Frame triples → poses (see the module docstring). Pure: no I/O, no threads.

    Parameters
    ----------
    geometry : Geometry
        The station's screens and camera mappings.
    compensate : callable, optional
        (6,) raw OPR pose [x, y, z, a, b, c] → (6,) corrected pose (e.g. a calibration record's
        correction wrapped by the caller). Applied before the tool transform.
    tool_in_opr : Pose, optional
        The ISO measuring point in the OPR frame; the sample's ``pose`` is then the tool's.
    clock : ClockModel or mapping "x"/"y"/"z" → ClockModel, optional
        Each camera's clock → the robot's; default: the cameras stamp on the robot's clock.
    max_residual_rms : float or None
        m, the solver's consistency limit (``solve_pose``).
    max_timestamp_spread : float
        s, three frames whose robot-clock times differ by more are not one trigger: dropped.
    """

    def __init__(
        self,
        geometry: Geometry,
        *,
        compensate: Callable[[np.ndarray], np.ndarray] | None = None,
        tool_in_opr: Pose | None = None,
        clock: ClockModel | Mapping[str, ClockModel] | None = None,
        max_residual_rms: float | None = DEFAULT_MAX_RESIDUAL_RMS,
        max_timestamp_spread: float = DEFAULT_MAX_TIMESTAMP_SPREAD,
    ) -> None:
        if not isinstance(geometry, Geometry):
            raise TypeError(f"geometry must be an instrument.pose.Geometry, got {type(geometry).__name__}")
        clock = ClockModel.identity() if clock is None else clock
        self._clocks = dict.fromkeys(SCREENS, clock) if isinstance(clock, ClockModel) else dict(clock)
        if set(self._clocks) != set(SCREENS) or not all(isinstance(c, ClockModel) for c in self._clocks.values()):
            raise TypeError("clock must be a ClockModel or a mapping x/y/z → ClockModel")
        if not (max_timestamp_spread > 0):
            raise ValueError(f"max_timestamp_spread must be positive, got {max_timestamp_spread!r}")
        self.geometry = geometry
        self.compensate = compensate
        self.tool_in_opr = tool_in_opr
        self.max_residual_rms = max_residual_rms
        self.max_timestamp_spread = float(max_timestamp_spread)
        self._rows: dict[str, list] = {name: [] for name in _COLUMNS}
        self._drops: list[Drop] = []
        self._last_index: int | None = None
        self._last_pose: Pose | None = None  # the previous solve: the next one's warm start

    # ------------------------------------------------------------------ one trigger
    def add(self, triple: FrameTriple) -> PoseSample | Drop:
        """The pose of one trigger, or the :class:`Drop` saying why there is none.

        A gap in the trigger numbers before this one is recorded as a drop of its own ("not
        received"); the returned value concerns this trigger only.
        """
        index = int(triple.index)
        if self._last_index is not None:
            if index <= self._last_index:
                return self._drop(index, 1, f"out of order: trigger {index} after {self._last_index}")
            if index > self._last_index + 1:
                self._drop(self._last_index + 1, index - self._last_index - 1, "not received")
        self._last_index = index
        failures = dict(triple.failures or {})
        missing = [s for s in SCREENS if triple.crosses.get(s) is None]
        if missing:
            why = "; ".join(f"screen {s}: {failures.get(s, 'no cross')}" for s in missing)
            return self._drop(index, 1, f"cross missing — {why}")
        try:
            times = [self._clocks[s].to_robot(float(triple.timestamps[s])) for s in SCREENS]
        except (KeyError, TypeError, ValueError):
            return self._drop(index, 1, "timestamps: expected one number per screen x, y, z")
        spread = max(times) - min(times)
        if not (math.isfinite(spread) and spread <= self.max_timestamp_spread):
            return self._drop(
                index, 1, f"frames not from one trigger: timestamps differ by {spread * 1e3:.3f} ms "
                f"(limit {self.max_timestamp_spread * 1e3:.3f} ms)",
            )
        crosses: dict[str, CrossMeasurement] = {}
        for s in SCREENS:
            cross = triple.crosses[s]
            assert cross is not None  # the missing ones were dropped above
            crosses[s] = cross
        try:
            estimate = self._solve(crosses)
        except PoseError as exc:
            self._last_pose = None
            return self._drop(index, 1, f"pose: {exc}")
        self._last_pose = estimate.pose
        raw = estimate.pose.as_iso()
        pose = raw if self.compensate is None else np.asarray(self.compensate(raw.copy()), dtype=float)
        if pose.shape != (6,):
            raise ValueError(f"compensate must return a (6,) pose, got shape {pose.shape}")
        if self.tool_in_opr is not None:
            pose = tool_pose(Pose.from_iso(pose), self.tool_in_opr).as_iso()
        lines = [line for c in crosses.values() for line in (c.horizontal, c.vertical)]
        sample = PoseSample(
            index=index,
            time=sum(times) / len(times),  # np.mean of three floats, without its overhead
            pose=pose,
            raw=raw,
            residual_rms=float(estimate.residual_rms),
            timestamp_spread=float(spread),
            min_sections=int(min(line.sections for line in lines)),
            max_line_rms=float(max(line.residual_rms for line in lines)),
            tracked=sum(getattr(c, "search", "full") == "tracked" for c in crosses.values()),
        )
        for name in _COLUMNS:
            self._rows[name].append(getattr(sample, name))
        return sample

    def _solve(self, crosses):
        """Warm start from the previous pose; if that fails, once more from the closed form."""
        if self._last_pose is not None:
            try:
                return solve_pose(crosses, self.geometry, max_residual_rms=self.max_residual_rms,
                                  initial=self._last_pose)
            except PoseError:
                pass
        return solve_pose(crosses, self.geometry, max_residual_rms=self.max_residual_rms)

    def _drop(self, index: int, count: int, reason: str) -> Drop:
        drop = Drop(index, count, reason)
        self._drops.append(drop)
        return drop

    def note_missing(self, index: int, reason: str) -> Drop:
        """Record a trigger that cannot be handed over as a triple (e.g. a frame lost in transfer)."""
        if self._last_index is not None and index <= self._last_index:
            return self._drop(index, 1, f"out of order: trigger {index} after {self._last_index}")
        if self._last_index is not None and index > self._last_index + 1:
            self._drop(self._last_index + 1, index - self._last_index - 1, "not received")
        self._last_index = index
        self._last_pose = None
        return self._drop(index, 1, reason)

    # ------------------------------------------------------------------ the result
    @property
    def samples(self) -> int:
        return len(self._rows["index"])

    @property
    def dropped(self) -> int:
        return sum(d.count for d in self._drops)

    def stream(self) -> PoseStream:
        """Everything so far as a :class:`PoseStream` (columns copied; the streamer can go on)."""
        drops = tuple(self._drops)
        if not self._rows["index"]:
            return _empty_stream(drops)
        rows = self._rows
        return PoseStream(
            index=np.array(rows["index"], np.int64),
            time=np.array(rows["time"]),
            pose=np.array(rows["pose"]),
            raw=np.array(rows["raw"]),
            residual_rms=np.array(rows["residual_rms"]),
            timestamp_spread=np.array(rows["timestamp_spread"]),
            min_sections=np.array(rows["min_sections"], np.int64),
            max_line_rms=np.array(rows["max_line_rms"]),
            tracked=np.array(rows["tracked"], np.int64),
            drops=drops,
        )


class PoseTracker:
    """Images → poses: :class:`PoseStreamer` with the vision in front, each cross tracked from the
    previous frame's (``locate_crosses(images, priors=last)``; the full search when there is no
    prior or it is lost).

    Parameters
    ----------
    geometry : Geometry
    saturation : float or mapping "x"/"y"/"z" → float, optional
        Sensor saturation level(s) (default: the dtype's full scale).
    search_px : int
        Half-width of the band searched around each prior line (``locate_cross``).
    **streamer
        Passed to :class:`PoseStreamer` (compensate, tool_in_opr, clock, max_residual_rms, …).
    """

    def __init__(self, geometry: Geometry, *, saturation=None, search_px: int = 24, **streamer) -> None:
        self.streamer = PoseStreamer(geometry, **streamer)
        self._saturation = saturation if isinstance(saturation, Mapping) else dict.fromkeys(SCREENS, saturation)
        self.search_px = search_px
        self._priors: dict[str, CrossMeasurement | None] = dict.fromkeys(SCREENS)
        self.fallbacks = 0  # crosses a lost prior sent back to the full search
        self._workspace = VisionWorkspace()  # the vision's scratch memory, reused trigger after trigger

    def add(self, index: int, timestamps: Mapping[str, float], images: Mapping[str, np.ndarray]) -> PoseSample | Drop:
        """Locate the three crosses of one trigger and solve its pose (see :meth:`PoseStreamer.add`).

        The three frames go through ``locate_crosses`` together (one fine stage for all six
        stripes); a frame that is missing or shows no usable cross clears that camera's prior.
        """
        crosses: dict[str, CrossMeasurement | None] = {}
        failures: dict[str, str] = {}
        present = {s: images[s] for s in SCREENS if images.get(s) is not None}
        for s in SCREENS:
            if s not in present:
                crosses[s], failures[s] = None, "no frame"
                self._priors[s] = None
        try:
            located = locate_crosses(present, self._saturation, self._priors, search_px=self.search_px,
                                     workspace=self._workspace)
        except ValueError as exc:  # a malformed frame (shape, saturation): none of this trigger is usable
            located = {s: CrossNotFound(f"unusable frame: {exc}") for s in present}
        for s, result in located.items():
            if isinstance(result, CrossNotFound):
                crosses[s], failures[s] = None, str(result)
                self._priors[s] = None
                continue
            if result.search == "fallback":
                self.fallbacks += 1
            crosses[s] = self._priors[s] = result
        return self.streamer.add(FrameTriple(index, timestamps, crosses, failures))

    def stream(self) -> PoseStream:
        return self.streamer.stream()
