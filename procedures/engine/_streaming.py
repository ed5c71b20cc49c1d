"""Acquiring the pose stream of one move measured in motion: the cameras streamed, the poses, the clocks.

``acquire_stream`` runs one measured motion: the cameras stream (``CameraTriplet.start_stream``) from
before the motion starts until ``hold_s`` after the robot reports it done, every triple becomes a pose
(``instrument.stream.PoseTracker``, compensated as the static kinds compensate, the tool transform
left to the analysis), and the camera timestamps are put on the controller's clock from the trigger
line's paired times (``FrameStream.sync_times``, ``instrument.stream.estimate_clock_offset``, one
model per camera). The tracker runs while the triples are read (a triple of three 1 MP frames is
3 MB; a move's frames are never all held), with the cameras' own clocks; the samples' times are
recomputed once the clock models are fitted from all the pairs, and the three frames of a sample
whose times then differ by more than ``MAX_TIMESTAMP_SPREAD_S`` are dropped (not one trigger). The
result is a ``procedures.kinds.StreamRecord``, what the kind analyses and the store keeps.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, Protocol

import numpy as np

from instrument import SCREENS
from procedures.kinds import StreamRecord

MAX_TIMESTAMP_SPREAD_S = 1e-3


class Tracker(Protocol):
    """Images → poses (``instrument.stream.PoseTracker``, or a test's fake)."""

    def add(self, index: int, timestamps: Mapping[str, float], images: Mapping[str, np.ndarray]) -> Any: ...

    def stream(self) -> Any:
        """Columns ``index``, ``time``, ``pose``, ``raw``, ``residual_rms``, ``tracked``; ``drops``."""
        ...


class Triple(Protocol):
    index: int
    frames: Mapping[str, Any]
    timestamps: Mapping[str, float]
    missing: Mapping[str, str]


class CameraStream(Protocol):
    """What ``drivers.camera.FrameStream`` offers (the fakes offer the same)."""

    rate_hz: float

    def stop(self) -> None: ...

    def __iter__(self) -> Any: ...

    def sync_times(self) -> np.ndarray | None: ...

    def close(self) -> None: ...


def clock_models(stamps: Mapping[str, Sequence[tuple[int, float]]], pulses: np.ndarray | None,
                 exposure_s: Mapping[str, float]) -> tuple[dict[str, Any], dict[str, Any]]:
    """Each camera's clock → the controller's, from (trigger, stamp) pairs and the pulses' controller
    times; ({camera: ClockModel}, what the fit says). Without pulses: identity, and the info says so."""
    from instrument.stream import ClockError, ClockModel, estimate_clock_offset

    models: dict[str, Any] = {}
    info: dict[str, Any] = {"source": "trigger line" if pulses is not None else "none (camera clocks taken as "
                            "the controller's)"}
    for camera in SCREENS:
        pairs = stamps.get(camera, ())
        if pulses is None or len(pairs) < 3:
            models[camera] = ClockModel.identity()
            continue
        index = np.array([k for k, _ in pairs if k < len(pulses)], dtype=int)
        camera_times = np.array([s for k, s in pairs if k < len(pulses)])
        try:
            # A pulse starts the exposure; a frame's stamp is its mean time: half the exposure later.
            model = estimate_clock_offset(camera_times, pulses[index] + 0.5 * exposure_s[camera])
        except (ClockError, ValueError) as exc:
            info[f"{camera}_error"] = str(exc)
            models[camera] = ClockModel.identity()
            continue
        models[camera] = model
        info[camera] = {"residual_rms": float(model.residual_rms), "max_residual": float(model.max_residual),
                        "pairs": int(model.pairs), "rejected": int(model.rejected),
                        "drift": float(model.drift)}
    return models, info


def retime(stream: Any, stamps: Mapping[int, Mapping[str, float]], models: Mapping[str, Any]
           ) -> tuple[np.ndarray, np.ndarray]:
    """(times, spreads) of the tracker's samples on the controller's clock: each sample's three
    camera stamps through their clock models, their mean and their spread."""
    times = np.empty(len(stream.index))
    spreads = np.empty(len(stream.index))
    for i, k in enumerate(np.asarray(stream.index, dtype=int)):
        on_robot = [float(models[c].to_robot(stamps[int(k)][c])) for c in SCREENS]
        times[i] = float(np.mean(on_robot))
        spreads[i] = max(on_robot) - min(on_robot)
    return times, spreads


def acquire_stream(start: Callable[[], CameraStream], motion: Callable[[], None], *, robot: Any,
                   hold_s: float, wait: Callable[[float], None], tracker: Tracker,
                   exposure_s: Mapping[str, float], check_abort: Callable[[], None] | None = None) -> StreamRecord:
    """Stream the cameras while ``motion()`` runs and ``hold_s`` after it; → the move's poses.

    Parameters
    ----------
    start : opens the camera stream (its pulses run from here)
    motion : the blocking measured move; the robot's ``last_move_done_time()`` after it is the signal
    robot : reads the done signal
    hold_s : s streamed after the motion returns (the ring-down window)
    wait : sleeps (an abort cuts it short)
    tracker : images → poses, with the camera clocks as they are (retimed here)
    exposure_s : per camera, s (a frame's stamp is its exposure's middle)
    """
    stream = start()
    try:
        motion()
        signal = robot.last_move_done_time()
        wait(hold_s)
        stream.stop()
        stamps: dict[int, dict[str, float]] = {}
        pairs: dict[str, list[tuple[int, float]]] = {c: [] for c in SCREENS}
        triggers = 0
        missing: dict[str, int] = {}
        for triple in stream:
            if check_abort is not None:
                check_abort()
            triggers += 1
            stamps[triple.index] = dict(triple.timestamps)
            for camera, stamp in triple.timestamps.items():
                pairs[camera].append((triple.index, float(stamp)))
            for reason in triple.missing.values():
                missing[reason] = missing.get(reason, 0) + 1
            tracker.add(triple.index, triple.timestamps,
                        {c: getattr(f, "image", f) for c, f in triple.frames.items()})
        pulses = stream.sync_times()
        rate = float(stream.rate_hz)
    finally:
        stream.close()
    poses = tracker.stream()
    models, clock = clock_models(pairs, pulses, exposure_s)
    times, spreads = retime(poses, stamps, models) if len(poses.index) else (np.empty(0), np.empty(0))
    keep = spreads <= MAX_TIMESTAMP_SPREAD_S
    reasons: dict[str, int] = {}
    for drop in getattr(poses, "drops", ()):
        key = str(drop.reason).split(":")[0][:80]
        reasons[key] = reasons.get(key, 0) + int(drop.count)
    if not np.all(keep):
        reasons["frames not from one trigger"] = reasons.get("frames not from one trigger", 0) + int(np.sum(~keep))
    record = StreamRecord(
        index=np.asarray(poses.index, dtype=np.int64)[keep], t=times[keep],
        pose=np.asarray(poses.pose, dtype=float).reshape(-1, 6)[keep],
        raw=np.asarray(poses.raw, dtype=float).reshape(-1, 6)[keep],
        residual_rms=np.asarray(poses.residual_rms, dtype=float)[keep], timestamp_spread=spreads[keep],
        tracked=np.asarray(poses.tracked, dtype=np.int64)[keep],
        meta={"rate_hz": rate, "exposure_s": dict(exposure_s), "triggers": triggers,
              "pulses": None if pulses is None else int(len(pulses)),
              "dropped": int(triggers - int(np.sum(keep))), "drop_reasons": reasons, "missing_frames": missing,
              "t_signal": None if signal is None else float(signal), "hold_s": float(hold_s), "clock": clock},
    )
    return record


def compensate_with(compensators: Sequence[Any], direction: Mapping[str, int | None] | None
                    ) -> Callable[[np.ndarray], np.ndarray] | None:
    """The stream's compensation: the records in force applied in order, as ``measure_pose`` applies them."""
    if not compensators:
        return None

    def correct(pose: np.ndarray) -> np.ndarray:
        corrected = np.asarray(pose, dtype=float)
        for compensator in compensators:
            corrected, _ = compensator.correct(corrected, direction)
        return np.asarray(corrected, dtype=float)

    return correct


def seconds_of(record: StreamRecord) -> Iterable[int]:
    """The last sample of every streamed second (indices into the record), for the live events."""
    if not len(record):
        return []
    second = np.floor(record.t - record.t[0]).astype(int)
    last = np.flatnonzero(np.append(np.diff(second) != 0, True))
    return [int(i) for i in last]


def distance_to(record: StreamRecord, target: np.ndarray) -> np.ndarray:
    """(N,) m, each sample's distance to ``target`` (3,)."""
    return np.linalg.norm(record.pose[:, :3] - np.asarray(target, dtype=float)[None, :], axis=1) if len(record) \
        else np.empty(0)
