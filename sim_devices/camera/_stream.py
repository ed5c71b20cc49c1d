"""Streaming acquisition in the simulated cell: the trigger line, the cameras' clocks, motion blur.

What a real cell has, and how the twin plays it
-----------------------------------------------
A real cell triggers the three cameras together on a common hardware line (``TriggerSource
Line1``, rising edge) from a trigger generator at the stream's rate; each camera exposes, stamps
the frame on its own clock (chunk ``Timestamp``, exposure start) and counts it (frame counter);
a camera still busy (exposure + readout of the previous frame) misses the pulse ("overtrigger").

Here the camera process plays the generator and the three camera heads. The pulses are on the
robot controller's clock (``t_k = t0 + k / rate``; the controller's clock runs on this machine's
monotonic clock from the origin the robot twin publishes in ``trajectories/clock.json``), and
their controller times are known exactly — what a controller stamping the pulse on a digital input
(or driving the line from a digital output itself) would provide for the clock pairing. Each
camera has a seeded clock (offset, drift, stamp jitter) and a readout time (rows × ``line_time``),
so a rate too high for the ROI misses pulses as a real sensor does. Every frame is rendered at the
TRUE pose of its exposure from the robot's dense truth (``sim_devices.trajectory``), the stripes
averaged over the exposure (motion blur, as many sub-poses as the motion needs).

The pylon emulator carries the images but not their chunk data, and it reads a directory's file
list once, when acquisition starts, and each file's content when it serves it (checked,
``tests/test_camera_stream.py``). So a stream is recorded, then replayed through the emulator:

1. the driver writes ``streams/<id>.start`` (rate, each camera's exposure and ROI); the twin
   answers ``<id>/started.json`` (``t0``, ``period``) and the pulses run from ``t0``;
2. the driver writes ``<id>.stop``; the twin fixes the pulses up to that instant, decides which
   each camera captured, and writes ``<id>/plan.json`` and a ring of ``slots`` placeholder files
   per camera, ``<id>/<camera>/slot-NNN.bmp``;
3. the twin renders frame j of each camera once the truth of its exposure is written and the
   driver has consumed frame j − slots (``<id>/<camera>.consumed``), puts it into slot j mod slots
   and appends its chunk data to ``<id>/<camera>.chunks`` (``j ticks``: frame counter, timestamp of
   the exposure start in camera ticks of 1 ns); ``<id>/done`` when all are written;
4. the driver points each emulated camera at its directory, triggers it once per frame (the
   emulator serves the slots in name order: block j is slot j mod slots) and reads the chunk line
   of the same number; ``<id>.close`` lets the twin delete the stream.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sim_devices._config import checked_fields
from sim_devices._transforms import matrix_to_rotvec
from sim_devices.camera._optics import AXIS_NAMES, OpticalBench
from sim_devices.trajectory import TrajectoryLog
from sim_devices.world import World

TICKS_PER_SECOND = 1_000_000_000
POLL = 0.005  # s between looks at the request directory and at a consumer's progress
# With no stream open and no request for a while, the twin looks at its directory this often (a start
# request waits at most this long; its stream's t0 lies ``start_lead`` ahead of the answer anyway):
# an idle cell must not burn a core's tenth on directory listings.
IDLE_POLL = 0.05
IDLE_AFTER = 2.0  # s without a request or an open stream before the twin polls at IDLE_POLL
SEQ_BASE = 1 << 40  # noise seeds of stream frames, apart from the static frame sets 1, 2, ...


@dataclass
class StreamConfig:
    """The simulated cameras' timing (the ``cameras`` section of a cell configuration).

    Attributes
    ----------
    line_time : float
        s to read one sensor row: a frame of ``h`` rows takes ``h · line_time``.
    frame_overhead : float
        s a camera needs between frames beyond its exposure or readout.
    trigger_delay : float
        s from the pulse to the exposure start.
    clock_drift_std : float
        Relative rate error of each camera's clock (σ, seeded).
    timestamp_jitter : float
        s, σ of each stamp.
    blur_step_px : float
        Most motion (px) between two sub-poses of a blurred exposure.
    max_blur_samples : int
        Most sub-poses per exposure.
    start_lead : float
        s from the start request to the first pulse.
    slots : int
        Files in each camera's ring (frames rendered ahead of the consumer).
    truth_margin : float
        s the robot's truth of an instant may still be written after it (a late controller cycle).
    abandon_after : float
        s without progress of the consumer after which a stream is given up.
    """

    line_time: float = 4.8e-6
    frame_overhead: float = 50e-6
    trigger_delay: float = 0.0
    clock_drift_std: float = 20e-6
    timestamp_jitter: float = 1e-6
    blur_step_px: float = 0.25
    max_blur_samples: int = 12
    start_lead: float = 0.005
    slots: int = 16
    truth_margin: float = 1.0
    abandon_after: float = 60.0

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> StreamConfig:
        values = checked_fields(cls, data, "cameras config")
        config = cls(**values)
        if min(config.line_time, config.frame_overhead, config.trigger_delay, config.clock_drift_std,
               config.timestamp_jitter) < 0 or config.blur_step_px <= 0 or config.max_blur_samples < 1 \
                or config.slots < 2 or config.truth_margin < 0 or config.abandon_after <= 0:
            raise ValueError("cameras config: timings must be ≥ 0, blur_step_px > 0, max_blur_samples ≥ 1, slots ≥ 2")
        return config

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(frozen=True)
class CameraClock:
    """One camera's clock: ``ticks = (offset + (1 + drift) · t_controller + jitter) · 1e9``."""

    offset: float
    drift: float
    jitter: float

    def ticks(self, t_controller: float, rng: np.random.Generator) -> int:
        seconds = self.offset + (1.0 + self.drift) * t_controller + self.jitter * rng.standard_normal()
        return int(round(seconds * TICKS_PER_SECOND))


def write_atomically(directory: Path, target: Path, data: bytes) -> None:
    """``target`` replaced in one step, its temporary file in ``directory`` (never the target's own
    directory: the emulator lists that one)."""
    tmp = directory / f".{target.name}.{os.getpid()}.{threading.get_ident()}.tmp"
    tmp.write_bytes(data)
    os.replace(tmp, target)


def _bmp(image: np.ndarray) -> bytes:
    ok, encoded = cv2.imencode(".bmp", image)
    if not ok:
        raise OSError("could not encode a BMP")
    return encoded.tobytes()


@dataclass
class _Camera:
    name: str
    exposure: float
    roi: tuple[int, int, int, int]
    captured: list[int]  # pulse numbers this camera exposed for
    next_frame: int = 0


class TwinStream:
    """One stream: its pulses, what each camera captured, its files (see the module docstring)."""

    def __init__(self, root: Path, stream_id: str, request: Mapping[str, Any], t0: float, number: int,
                 config: StreamConfig, sizes: Mapping[str, tuple[int, int]]) -> None:
        self.id = stream_id
        self.dir = root / stream_id
        self.rate = float(request["rate_hz"])
        if not 0 < self.rate <= 10_000:
            raise ValueError(f"stream rate must be in (0, 10000] Hz, got {self.rate}")
        self.period = 1.0 / self.rate
        self.t0 = t0
        self.number = number
        self.config = config
        self.cameras: dict[str, _Camera] = {}
        for name, spec in dict(request.get("cameras") or {}).items():
            if name not in AXIS_NAMES:
                raise ValueError(f"stream: no camera {name!r}")
            width, height = sizes[name]
            roi = tuple(int(v) for v in spec.get("roi") or (0, 0, width, height))
            if len(roi) != 4 or roi[0] < 0 or roi[1] < 0 or roi[2] <= 0 or roi[3] <= 0 \
                    or roi[0] + roi[2] > width or roi[1] + roi[3] > height:
                raise ValueError(f"stream: roi {roi} of camera {name} does not fit its {width} x {height} sensor")
            exposure = float(spec.get("exposure_s") or 1e-3)
            if not 0 < exposure < 1:
                raise ValueError(f"stream: exposure of camera {name} must be in (0, 1) s, got {exposure}")
            self.cameras[name] = _Camera(name, exposure, (roi[0], roi[1], roi[2], roi[3]), [])
        if not self.cameras:
            raise ValueError("stream: no cameras requested")
        self.triggers = 0
        self.stopped = False
        self.done = False
        self.last_progress = time.monotonic()

    def stop(self, t_stop: float) -> None:
        """Fix the pulses up to ``t_stop`` and which of them each camera captured."""
        self.triggers = max(0, int(math.floor((t_stop - self.t0) / self.period)) + 1)
        for camera in self.cameras.values():
            busy_for = max(camera.exposure, camera.roi[3] * self.config.line_time) + self.config.frame_overhead
            ready_at = -math.inf
            for k in range(self.triggers):
                t = self.t0 + k * self.period
                if t >= ready_at - 1e-12:  # idle: this pulse starts an exposure
                    camera.captured.append(k)
                    ready_at = t + busy_for
        self.stopped = True

    def consumed(self, camera: str) -> int:
        try:
            return int((self.dir / f"{camera}.consumed").read_text().strip() or -1)
        except (OSError, ValueError):
            return -1


class StreamServer:
    """Serves the stream requests of a camera twin (see the module docstring).

    Parameters
    ----------
    world : World
        The true constants (OPR mounting, M) and, without a robot's truth, the pose.
    bench : OpticalBench
    renderer_seed : int
        Noise seed of the stream frames (seq ``SEQ_BASE + stream · 2^20 + frame``).
    root : path
        ``<frames>/streams``: where requests come and streams go.
    trajectories : path or None
        The robot's trajectory directory (its dense truth and clock); None: the world's pose.
    config : StreamConfig
    """

    def __init__(self, world: World, bench: OpticalBench, renderer_seed: int, root: Path, trajectories: Path | None,
                 config: StreamConfig) -> None:
        # Imported here: the cell's supervisor reads StreamConfig from this module and never renders
        # (the renderer's SciPy is a third of a second of every cell start).
        from sim_devices.camera._renderer import Renderer

        self.world = world
        self.bench = bench
        self.renderer = Renderer(bench, seed=renderer_seed, bit_depth=8, session=world.config.session)
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.truth = TrajectoryLog(trajectories) if trajectories is not None else None
        self.config = config
        rng = world.rng("camera-clocks")
        self.clocks = {name: CameraClock(float(rng.uniform(10.0, 1000.0)),
                                         float(rng.normal(0.0, config.clock_drift_std)), config.timestamp_jitter)
                       for name in AXIS_NAMES}
        self._stamp_rng = {name: world.rng(f"camera-stamps-{name}") for name in AXIS_NAMES}
        self._own_origin = time.monotonic()
        self._streams: dict[str, TwinStream] = {}
        self._started = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.frames_rendered = 0
        self.errors: list[str] = []

    # ----------------------------------------------------------------------------- lifecycle
    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name="camera-streams", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(10.0)
            self._thread = None

    def stats(self) -> dict[str, Any]:
        return {"streams": self._started, "frames_rendered": self.frames_rendered, "errors": list(self.errors[-5:]),
                "clocks": {k: {"offset": c.offset, "drift": c.drift} for k, c in self.clocks.items()}}

    # ----------------------------------------------------------------------------- clocks and truth
    def controller_now(self) -> float:
        """The controller's clock now (its origin from the robot twin; this twin's start without one)."""
        clock = self.truth.clock() if self.truth is not None else None
        origin = float(clock["monotonic_origin"]) if clock else self._own_origin
        return time.monotonic() - origin

    def truth_until(self, now: float) -> float:
        """Controller time up to which the true pose is known for certain."""
        if self.truth is None:
            return now
        return min(now - self.config.truth_margin, self.truth.known_until())

    def opr_at(self, times: np.ndarray) -> np.ndarray:
        """True OPR poses in M (n, 4, 4) at controller ``times``."""
        state = self.world.state()
        if self.truth is None or state.mount != "robot":
            return np.repeat(state.opr_in_m[None], len(times), axis=0)
        flange = self.truth.flange_at(times, rest=self.world.reference_flange_pose)
        return np.linalg.inv(self.world.base_to_m)[None] @ flange @ self.world.true_opr_mount[None]

    # ----------------------------------------------------------------------------- serving
    def _serve(self) -> None:
        busy_at = time.monotonic()
        while not self._stop.is_set():
            try:
                worked = self._requests() | self._render_some()
            except Exception as exc:  # a broken stream must not end the service
                self.errors.append(f"{type(exc).__name__}: {exc}")
                worked = False
            if worked or self._streams:
                busy_at = time.monotonic()
            if not worked:
                self._stop.wait(POLL if time.monotonic() - busy_at < IDLE_AFTER else IDLE_POLL)

    def _requests(self) -> bool:
        worked = False
        for path in sorted(self.root.glob("*.start")):
            worked = True
            stream_id = path.stem
            try:
                request = json.loads(path.read_text())
                self._started += 1
                t0 = self.controller_now() + self.config.start_lead
                sizes = {name: self.bench.cameras[name].size_px for name in AXIS_NAMES}
                stream = TwinStream(self.root, stream_id, request, t0, self._started, self.config, sizes)
                stream.dir.mkdir(parents=True, exist_ok=True)
                self._streams[stream_id] = stream
                answer: dict[str, Any] = {"t0": t0, "period": stream.period}
            except (ValueError, KeyError, TypeError) as exc:
                (self.root / stream_id).mkdir(parents=True, exist_ok=True)
                answer = {"error": str(exc)}
            write_atomically(self.root, self.root / stream_id / "started.json", json.dumps(answer).encode())
            path.unlink(missing_ok=True)
        for path in sorted(self.root.glob("*.stop")):
            worked = True
            stopping = self._streams.get(path.stem)
            if stopping is not None and not stopping.stopped:
                self._plan(stopping, self.controller_now())
            path.unlink(missing_ok=True)
        for path in sorted(self.root.glob("*.close")):
            worked = True
            self._close(path.stem)
            path.unlink(missing_ok=True)
        for stream in list(self._streams.values()):
            if time.monotonic() - stream.last_progress > self.config.abandon_after:
                self.errors.append(f"stream {stream.id} abandoned: no progress for {self.config.abandon_after} s")
                self._close(stream.id)
        return worked

    def _plan(self, stream: TwinStream, t_stop: float) -> None:
        stream.stop(t_stop)
        for camera in stream.cameras.values():
            directory = stream.dir / camera.name
            directory.mkdir(exist_ok=True)
            placeholder = stream.dir / f"{camera.name}.placeholder.bmp"
            write_atomically(stream.dir, placeholder, _bmp(np.zeros((camera.roi[3], camera.roi[2]), np.uint8)))
            for slot in range(min(self.config.slots, max(len(camera.captured), 1))):
                os.link(placeholder, directory / f"slot-{slot:03d}.bmp")
            (stream.dir / f"{camera.name}.chunks").touch()
        plan = {"triggers": stream.triggers, "t0": stream.t0, "period": stream.period,
                "slots": self.config.slots, "tick_frequency": TICKS_PER_SECOND,
                "frames": {c.name: len(c.captured) for c in stream.cameras.values()},
                "exposure_s": {c.name: c.exposure for c in stream.cameras.values()},
                "roi": {c.name: list(c.roi) for c in stream.cameras.values()}}
        write_atomically(self.root, stream.dir / "plan.json", json.dumps(plan).encode())
        stream.last_progress = time.monotonic()

    def _close(self, stream_id: str) -> None:
        stream = self._streams.pop(stream_id, None)
        directory = stream.dir if stream is not None else self.root / stream_id
        if directory.is_dir() and directory.parent == self.root:
            for path in sorted(directory.rglob("*"), key=lambda p: len(p.parts), reverse=True):
                path.rmdir() if path.is_dir() else path.unlink(missing_ok=True)
            directory.rmdir()

    def _render_some(self) -> bool:
        """Render the next frame of every camera of every stopped stream that can have one now."""
        worked = False
        if not self._streams:
            return False
        now = self.controller_now()
        for stream in list(self._streams.values()):
            if not stream.stopped or stream.done:
                continue
            known = self.truth_until(now)
            finished = True
            for camera in stream.cameras.values():
                j = camera.next_frame
                if j >= len(camera.captured):
                    continue
                finished = False
                k = camera.captured[j]
                start = stream.t0 + k * stream.period + self.config.trigger_delay
                if start + camera.exposure > known:
                    continue  # the truth of this exposure is not written yet
                if j - stream.consumed(camera.name) > self.config.slots:
                    continue  # the ring is full: the consumer has not read slot j − slots yet
                self._render(stream, camera, j, start)
                camera.next_frame += 1
                stream.last_progress = time.monotonic()
                worked = True
            if finished:
                stream.done = True
                write_atomically(self.root, stream.dir / "done", b"")
        return worked

    def _render(self, stream: TwinStream, camera: _Camera, j: int, start: float) -> None:
        middle, blur = exposure_poses(self.bench, self.opr_at, start, camera.exposure, self.config.blur_step_px,
                                      self.config.max_blur_samples)
        seq = SEQ_BASE + (stream.number << 20) + j
        image = self.renderer.render(camera.name, middle, seq=seq, roi=camera.roi, blur=blur,
                                     exposure_scale=camera.exposure / 1e-3)
        slot = stream.dir / camera.name / f"slot-{j % self.config.slots:03d}.bmp"
        write_atomically(stream.dir, slot, _bmp(image))
        ticks = self.clocks[camera.name].ticks(start, self._stamp_rng[camera.name])
        with open(stream.dir / f"{camera.name}.chunks", "a") as handle:
            handle.write(f"{j} {ticks}\n")
        self.frames_rendered += 1


def blur_sample_count(bench: OpticalBench, first: np.ndarray, last: np.ndarray, step_px: float,
                      max_samples: int) -> int:
    """Sub-poses an exposure from pose ``first`` to ``last`` needs: its motion on the screen (the
    beam's lever of about one screen distance) in pixels, over ``step_px``, at most ``max_samples``."""
    lever = float(bench.config.screen_distance)
    moved = float(np.linalg.norm(last[:3, 3] - first[:3, 3])) + lever * float(
        np.linalg.norm(matrix_to_rotvec(last[:3, :3] @ first[:3, :3].T)))
    pixels = moved / float(bench.config.metres_per_px)
    return int(min(max_samples, max(1, math.ceil(pixels / step_px))))


def exposure_poses(bench: OpticalBench, opr_at: Callable[[np.ndarray], np.ndarray], start: float, exposure: float,
                   step_px: float, max_samples: int) -> tuple[np.ndarray, list[np.ndarray] | None]:
    """What ``Renderer.render`` needs for an exposure from ``start`` for ``exposure`` s: the OPR pose at
    its middle and, when the OPR moves enough to show, the sub-poses spread over it (``blur``; None for
    a sharp frame). ``opr_at(times)`` gives the true OPR poses (n, 4, 4) at those instants."""
    ends = opr_at(np.array([start, start + exposure]))
    samples = blur_sample_count(bench, ends[0], ends[1], step_px, max_samples)
    middle = opr_at(np.array([start + 0.5 * exposure]))[0]
    if samples <= 1:
        return middle, None
    times = start + (np.arange(samples) + 0.5) / samples * exposure
    return middle, list(opr_at(times))


def control_commands(server: StreamServer) -> dict[str, Callable[..., Any]]:
    """The stream part of the camera twin's control API."""
    return {"stream_stats": server.stats}
