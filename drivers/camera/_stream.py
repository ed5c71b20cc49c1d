"""Streaming acquisition: the three cameras triggered together at a set rate, frames as triples.

``CameraTriplet.start_stream(rate_hz, ...)`` returns a ``FrameStream``: iterate it for
``StreamTriple``s in trigger order — one per trigger, each with the frames that came, every
camera's timestamp (its own clock, seconds, the image's mean time: exposure start + half the
exposure) and frame counter, and for every camera without a frame the reason (a missed trigger, a
frame that did not arrive whole). Nothing is filled in: a trigger no camera captured is still a
triple, with all three missing.

Trigger numbers come from each camera's timestamps: ``k = round((t − t_first) · rate)`` from its
first frame of the stream (every camera is armed and idle at the first pulse, so the first pulse
reaches all three). A camera that misses pulses (still exposing or reading out: a rate too high
for its ROI) leaves gaps; they are counted in ``stats``.

Where the pulses come from
--------------------------
- **A real cell** (``hardware_trigger=True``): a common line into every camera's ``Line1``
  (``TriggerSource``, rising edge), driven by the cell's trigger generator at ``rate_hz`` — best the
  robot controller's own digital output, so that the controller knows each pulse's time on its own
  clock (the pairs for ``instrument.stream.estimate_clock_offset``); chunk ``Timestamp`` and frame
  counter come with each frame. A reader thread per camera collects the frames as they arrive.
  ``hardware_trigger=False``: this process fires software triggers at ``rate_hz`` (host-timed).
- **pylon's camera emulator** (``emulator_image`` set: the simulated cell): its lines never fire and
  its ``TimeStamp`` is 0, so the cell's camera twin plays the trigger line and the camera heads and
  the emulator carries the images (``sim_devices.camera``): the stream is recorded between
  ``start_stream`` and ``stop()`` and replayed afterwards — the driver points each emulated camera
  at the stream's frame directory and triggers it once per frame, and reads each frame's chunk data
  (counter, timestamp) from the file the twin writes beside it. Its frames come only after
  ``stop()``; ``sync_times()`` gives the pulses' controller times.
"""

from __future__ import annotations

import json
import os
import threading
import time
import uuid
from collections import deque
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivers._errors import DeviceError, DeviceTimeout
from drivers.camera._aravis import AravisCamera
from drivers.camera._interface import Frame, Roi
from drivers.camera._pylon import PylonCamera

PROTOCOL_TIMEOUT = 10.0  # s the simulated trigger line may take to answer a request
EMULATED_FRAME_TIMEOUT = 10.0  # s: the longest wait for a replayed frame (see _EmulatedFeed.peek)
# The adapters with the stream methods (stream_begin/fire/fetch/end): pylon (live, or its emulator
# replaying the simulated cell's recording) and Aravis (always live).
StreamingCamera = PylonCamera | AravisCamera


@dataclass(frozen=True)
class StreamTriple:
    """The frames of one trigger.

    Attributes
    ----------
    index : int
        Trigger number, from 0.
    frames : mapping camera → Frame
        The frames that came (``frame.frame_id`` is the camera's counter).
    timestamps : mapping camera → float
        s on each camera's own clock: the image's mean time (exposure start + exposure / 2).
    frame_ids : mapping camera → int
    missing : mapping camera → str
        The cameras without a frame, and why.
    """

    index: int
    frames: Mapping[str, Frame]
    timestamps: Mapping[str, float]
    frame_ids: Mapping[str, int]
    missing: Mapping[str, str]

    @property
    def complete(self) -> bool:
        return not self.missing


@dataclass
class StreamStats:
    """What a stream delivered: ``triggers`` (pulses, when known), ``triples`` handed out,
    ``complete`` ones, per camera ``frames``, ``missed`` (triggers without a frame: not captured)
    and ``lost`` (frames that did not arrive whole)."""

    triggers: int | None = None
    triples: int = 0
    complete: int = 0
    frames: dict[str, int] = field(default_factory=dict)
    missed: dict[str, int] = field(default_factory=dict)
    lost: dict[str, int] = field(default_factory=dict)


@dataclass
class _Item:
    counter: int
    seconds: float  # camera clock, image mean time
    frame: Frame | None
    failure: str | None


class _Feed:
    """One camera's frames in arrival order, with their trigger numbers."""

    def __init__(self, name: str, camera: StreamingCamera, period: float, exposure: float) -> None:
        self.name = name
        self.camera = camera
        self.period = period
        self.exposure = exposure
        self.tick_frequency = 1e9
        self._first: float | None = None

    def trigger_of(self, seconds: float) -> int:
        if self._first is None:
            self._first = seconds
        return int(round((seconds - self._first) / self.period))

    def peek(self) -> tuple[int, _Item] | None | bool:
        """(trigger, item) of the next frame; None if it has not come yet; False if the feed ended."""
        raise NotImplementedError

    def pop(self) -> None:
        raise NotImplementedError


class _EmulatedFeed(_Feed):
    """Replays the simulated cell's recording of one camera through the emulator."""

    def __init__(self, name: str, camera: PylonCamera, period: float, exposure: float, directory: Path,
                 frames: int, tick_frequency: float) -> None:
        super().__init__(name, camera, period, exposure)
        self.camera: PylonCamera = camera
        self.directory = directory
        self.frames = frames
        self.tick_frequency = tick_frequency
        self._chunks: list[int] = []
        self._offset = 0
        self._next = 0
        self._item: tuple[int, _Item] | None = None

    def _read_chunks(self) -> None:
        path = self.directory / f"{self.name}.chunks"
        with open(path, "rb") as handle:
            handle.seek(self._offset)
            data = handle.read()
        complete = data[: data.rfind(b"\n") + 1]
        self._offset += len(complete)
        for line in complete.decode().splitlines():
            number, ticks = line.split()
            if int(number) != len(self._chunks):
                raise DeviceError(self.camera._device, "read chunk data", f"frame {number} out of order")
            self._chunks.append(int(ticks))

    def peek(self) -> tuple[int, _Item] | None | bool:
        if self._item is not None:
            return self._item
        if self._next >= self.frames:
            return False
        if self._next >= len(self._chunks):
            self._read_chunks()
            if self._next >= len(self._chunks):
                return None
        j = self._next
        self.camera.stream_fire()
        # The emulator serves a file that is already written: only a starved host makes it late, so the
        # camera's own grab timeout (2 s by default) is too short for a replay on a loaded machine.
        timeout = max(self.camera.timeout_s, EMULATED_FRAME_TIMEOUT)
        result = self.camera.stream_fetch(timeout)
        if result is None:
            raise DeviceTimeout(self.camera._device, "retrieve frame", f"no frame within {timeout:.3g} s")
        frame, block, _, failure = result
        if block != j:
            raise DeviceError(self.camera._device, "replay stream", f"the emulator served block {block}, expected {j}")
        seconds = self._chunks[j] / self.tick_frequency + 0.5 * self.exposure
        item = _Item(j, seconds, frame, failure)
        self._item = (self.trigger_of(seconds), item)
        _write_text(self.directory, self.directory / f"{self.name}.consumed", str(j))
        return self._item

    def pop(self) -> None:
        self._item = None
        self._next += 1


class _LiveFeed(_Feed):
    """A real camera's frames, collected by a reader thread as they arrive."""

    def __init__(self, name: str, camera: StreamingCamera, period: float, exposure: float) -> None:
        super().__init__(name, camera, period, exposure)
        self._queue: deque[_Item] = deque()
        self._lock = threading.Lock()
        self.stopped = threading.Event()
        self.error: DeviceError | None = None
        self._idle_since = time.monotonic()
        self._thread = threading.Thread(target=self._read, name=f"camera-{name}-stream", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _read(self) -> None:
        while True:
            try:
                result = self.camera.stream_fetch(0.05)
            except DeviceError as error:
                self.error = error
                return
            if result is None:
                if self.stopped.is_set() and time.monotonic() - self._idle_since > 4 * self.period + 0.1:
                    return  # stopped and drained
                continue
            self._idle_since = time.monotonic()
            frame, block, ticks, failure = result
            seconds = (ticks / self.tick_frequency if ticks else time.time()) + 0.5 * self.exposure
            with self._lock:
                self._queue.append(_Item(block, seconds, frame, failure))

    def peek(self) -> tuple[int, _Item] | None | bool:
        if self.error is not None:
            raise self.error
        with self._lock:
            if self._queue:
                item = self._queue[0]
                return self.trigger_of(item.seconds), item
        return False if not self._thread.is_alive() else None

    def pop(self) -> None:
        with self._lock:
            self._queue.popleft()

    def join(self, timeout: float) -> None:
        self._thread.join(timeout)


class FrameStream:
    """A running stream (see the module docstring). Iterate it for ``StreamTriple``s; ``stop()``
    ends the pulses; ``close()`` (or leaving a ``with`` block) puts the cameras back to single grabs.

    Parameters are set by ``CameraTriplet.start_stream``.
    """

    def __init__(self, cameras: Mapping[str, StreamingCamera], rate_hz: float, exposures: Mapping[str, float],
                 rois: Mapping[str, Roi | None], hardware_trigger: bool, timeout: float, name: str) -> None:
        if not 0 < rate_hz <= 10_000:
            raise ValueError(f"stream rate must be in (0, 10000] Hz, got {rate_hz!r}")
        self.cameras = dict(cameras)
        self.rate_hz = float(rate_hz)
        self.period = 1.0 / self.rate_hz
        self.exposures = dict(exposures)
        self.rois = dict(rois)
        self.hardware_trigger = hardware_trigger
        self.timeout = float(timeout)
        self.name = name
        self.stats = StreamStats(frames=dict.fromkeys(self.cameras, 0), missed=dict.fromkeys(self.cameras, 0),
                                 lost=dict.fromkeys(self.cameras, 0))
        self.emulated = all(c.emulated for c in self.cameras.values())
        if not self.emulated and any(c.emulated for c in self.cameras.values()):
            raise ValueError(f"{name}: a stream needs all cameras emulated or none")
        self._feeds: dict[str, _Feed] = {}
        self._stopped = False
        self._closed = False
        self._next = 0
        self._plan: dict[str, Any] | None = None
        self._started: dict[str, Any] | None = None
        self._software: threading.Thread | None = None
        self._stop_software = threading.Event()
        self._id = uuid.uuid4().hex[:12]
        self._root: Path | None = None
        if self.emulated:
            first = next(iter(self.cameras.values()))
            assert isinstance(first, PylonCamera) and first.emulator_image is not None
            self._root = first.emulator_image.parent / "streams"
            self._start_emulated()
        else:
            self._start_live()

    # ----------------------------------------------------------------------------- the pulses
    def _start_emulated(self) -> None:
        root = self._root
        assert root is not None
        if not root.is_dir():
            raise DeviceError(self.name, "start stream",
                              f"the simulated trigger line is not served ({root} is missing)")
        request = {"rate_hz": self.rate_hz, "cameras": {
            key: {"exposure_s": self.exposures[key],
                  "roi": None if self.rois[key] is None else _roi_list(self.rois[key])} for key in self.cameras}}
        _write_text(root, root / f"{self._id}.start", json.dumps(request))
        self._started = _wait_json(root / self._id / "started.json", PROTOCOL_TIMEOUT, self.name, "start stream")
        if "error" in self._started:
            raise DeviceError(self.name, "start stream",
                              f"the simulated trigger line refused: {self._started['error']}")

    def _start_live(self) -> None:
        source = "Line1" if self.hardware_trigger else "Software"
        for key, camera in self.cameras.items():
            line = camera.trigger_source if camera.trigger_source not in (None, "Software") else "Line1"
            frequency = camera.stream_begin(exposure_s=self.exposures[key], roi=self.rois[key],
                                            trigger_source=line if self.hardware_trigger else source)
            live = _LiveFeed(key, camera, self.period, self.exposures[key])
            live.tick_frequency = frequency
            self._feeds[key] = live
        for feed in self._feeds.values():
            assert isinstance(feed, _LiveFeed)
            feed.start()
        if not self.hardware_trigger:
            self._software = threading.Thread(target=self._fire, name=f"{self.name}-software-trigger", daemon=True)
            self._software.start()

    def _fire(self) -> None:
        """Software triggers at the set rate, on this host's clock (``hardware_trigger=False``)."""
        start = time.monotonic()
        k = 0
        while not self._stop_software.is_set():
            delay = start + k * self.period - time.monotonic()
            if delay > 0:
                self._stop_software.wait(delay)
                continue
            for camera in self.cameras.values():
                try:
                    camera.stream_fire()
                except DeviceError:
                    pass  # its feed reports the camera's trouble
            k += 1

    def stop(self) -> None:
        """End the pulses. An emulated stream's frames become available now (they are rendered and
        replayed after this); a real one's still in flight are collected."""
        if self._stopped:
            return
        self._stopped = True
        if self.emulated:
            root = self._root
            assert root is not None
            _write_text(root, root / f"{self._id}.stop", "")
            self._plan = _wait_json(root / self._id / "plan.json", PROTOCOL_TIMEOUT, self.name, "stop stream")
            self.stats.triggers = int(self._plan["triggers"])
            for key, camera in self.cameras.items():
                directory = root / self._id
                assert isinstance(camera, PylonCamera)
                camera.stream_begin(exposure_s=self.exposures[key], roi=self.rois[key], trigger_source="Software",
                                    sequence=directory / key)
                self._feeds[key] = _EmulatedFeed(key, camera, self.period, self.exposures[key], directory,
                                                 int(self._plan["frames"].get(key, 0)),
                                                 float(self._plan["tick_frequency"]))
        else:
            self._stop_software.set()
            for feed in self._feeds.values():
                assert isinstance(feed, _LiveFeed)
                feed.stopped.set()

    def sync_times(self) -> np.ndarray | None:
        """Controller-clock times (s) of the pulses, when the cell knows them (the simulated cell's
        trigger line does, after ``stop()``); None otherwise."""
        if self._plan is None:
            return None
        return float(self._plan["t0"]) + np.arange(int(self._plan["triggers"])) * float(self._plan["period"])

    # ----------------------------------------------------------------------------- the triples
    def __iter__(self) -> Iterator[StreamTriple]:
        while True:
            triple = self.next_triple()
            if triple is None:
                return
            yield triple

    def next_triple(self) -> StreamTriple | None:
        """The next trigger's triple, or None at the end of the stream; waits at most ``timeout`` s."""
        if self.emulated and not self._stopped:
            raise RuntimeError(f"{self.name}: an emulated stream delivers its frames after stop()")
        deadline = time.monotonic() + self.timeout
        k = self._next
        while True:
            heads = {key: feed.peek() for key, feed in self._feeds.items()}
            for key, head in heads.items():  # frames of earlier triggers (a repeated stamp): not this triple's
                while isinstance(head, tuple) and head[0] < k:
                    self._feeds[key].pop()
                    head = heads[key] = self._feeds[key].peek()
            waiting = [key for key, head in heads.items() if head is None]
            known_end = self.stats.triggers
            if not waiting:
                ended = all(head is False for head in heads.values())
                if ended and (known_end is None or k >= known_end):
                    return None
                break
            if time.monotonic() > deadline:
                raise DeviceTimeout(self.name, "stream", f"no frame of trigger {k} from camera(s) "
                                    f"{', '.join(waiting)} within {self.timeout:.3g} s")
            time.sleep(0.002)
        frames: dict[str, Frame] = {}
        stamps: dict[str, float] = {}
        ids: dict[str, int] = {}
        missing: dict[str, str] = {}
        for key, head in heads.items():
            if isinstance(head, tuple) and head[0] == k:
                item = head[1]
                self._feeds[key].pop()
                if item.frame is None:
                    missing[key] = f"frame {item.counter} did not arrive whole: {item.failure}"
                    self.stats.lost[key] += 1
                    continue
                frames[key], stamps[key], ids[key] = item.frame, item.seconds, item.counter
                self.stats.frames[key] += 1
            else:
                missing[key] = "trigger missed (the camera was still busy, or the pulse did not reach it)"
                self.stats.missed[key] += 1
        self._next = k + 1
        self.stats.triples += 1
        self.stats.complete += not missing
        return StreamTriple(k, frames, stamps, ids, missing)

    # ----------------------------------------------------------------------------- the end
    def close(self) -> None:
        """Stop, put every camera back to single grabs, let the simulated line drop its recording."""
        if self._closed:
            return
        self._closed = True
        try:
            if not self._stopped and not self.emulated:
                self.stop()
            for feed in self._feeds.values():
                if isinstance(feed, _LiveFeed):
                    feed.join(1.0)
        finally:
            try:
                for camera in self.cameras.values():
                    camera.stream_end()
            finally:
                if self._root is not None:
                    _write_text(self._root, self._root / f"{self._id}.close", "")

    def __enter__(self) -> FrameStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _roi_list(roi: Roi | None) -> list[int] | None:
    return None if roi is None else [roi.offset_x, roi.offset_y, roi.width, roi.height]


def _write_text(directory: Path, path: Path, text: str) -> None:
    tmp = directory / f".{path.name}.{os.getpid()}.tmp"
    tmp.write_text(text)
    os.replace(tmp, path)


def _wait_json(path: Path, timeout: float, device: str, operation: str) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        try:
            return dict(json.loads(path.read_text()))
        except (OSError, ValueError):
            pass
        if time.monotonic() > deadline:
            raise DeviceTimeout(device, operation, f"the simulated trigger line did not answer within {timeout:.3g} s "
                                f"({path.name})")
        time.sleep(0.005)
