"""Camera twins: image files for the pylon emulator, and an in-process ``Camera`` for unit tests.

``CameraFileTwin`` renders the three frames on every settled world state and replaces the files
the pylon emulator serves (``ImageFilename``) **before** the world's ``set_*`` call returns (in a
cell of processes: before every process's subscribers have acknowledged the state), so once a
robot twin reports "move done", any grab triggered after that sees the new pose, never a stale
frame. The pylon adapter restarts acquisition when the file changed (the emulator reads it then).

``SimCamera`` implements ``drivers.camera.Camera`` (plus ``trigger``/``retrieve``) by rendering
directly from the world, without pypylon.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from drivers import DeviceConnectionError, DeviceTimeout
from drivers.camera import Frame, GrabFailed, Roi
from sim_devices.camera._optics import AXIS_NAMES, OpticalBench
from sim_devices.camera._renderer import Renderer
from sim_devices.camera._stamp import stamp_bmp_file, stamp_image
from sim_devices.camera._stream import StreamConfig, StreamServer
from sim_devices.control import dispatch
from sim_devices.faults import FaultKind, FaultPlan
from sim_devices.world import World, WorldState, pose_record


def write_bmp_atomically(path: Path, image: np.ndarray) -> None:
    """Write an 8-bit BMP so that a reader sees the old file or the new one, never a partial one."""
    ok, encoded = cv2.imencode(".bmp", image)
    if not ok:
        raise OSError(f"could not encode {path.name} as BMP")
    write_atomically(path, encoded.tobytes())


def write_atomically(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that a reader sees the old file or the new one, never a partial one."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as handle:
        handle.write(data)
    os.replace(tmp, path)  # atomic within one directory


@dataclass
class _AheadFrames:
    """The frames of an announced pose, rendered ahead of time into hidden files."""

    index: int  # the frame set they are numbered (and seeded) as
    opr_in_m: np.ndarray
    scale: float
    paths: dict[str, Path]
    state: str = "wanted"  # wanted → rendering → done; "taken" when the settled state came first; "failed"


class CameraFileTwin:
    """Keeps ``<directory>/x.bmp``, ``y.bmp``, ``z.bmp`` showing the current settled true pose.

    On every settled world state the three frames are replaced (write, then rename) before the
    twin's subscriber returns, so once a robot twin reports "move done" — which it does only after
    every subscriber has seen the settled pose — a grab shows the new pose, never a stale frame.
    When a move is announced (``World.announce``: the robot knows its attained end pose when it
    plans the move) the frames for that pose are rendered ahead, on a worker thread, while the arm
    moves; the settled state then only renames them into place.

    Parameters
    ----------
    world : World
    bench : OpticalBench
    directory : path
        Created if missing. Point each emulated camera's ``ImageFilename`` at its file.
    seed : int, optional
        Noise seed (default: the world's seed); the noise of frame set ``n`` (the n-th rendered,
        ``frames_written``) is seeded by ``(seed, camera, n)``.
    stream : StreamConfig or mapping, optional
        The cameras' timing for streaming acquisition (``sim_devices.camera``); its requests
        come through ``<directory>/streams``.
    trajectories : path, optional
        The robot's dense truth (``sim_devices.trajectory``): streamed frames show the true pose of
        their exposure. Without it they show the world's current pose.
    render_delay : float
        Seconds each settled frame set takes on top of its rendering (a slow renderer on demand: the
        cell's race tests; ``cameras.render_delay`` in a cell configuration). 0 by default.
    stamp_frames : bool
        Embed a frame stamp (``sim_devices.camera._stamp``: frame number, and the host time since which
        the scene it shows has been still) in the first pixels of every frame put in place, so a reader
        can prove a frame was exposed after a move ended. A cell stamps its frames; off by default.
    """

    def __init__(self, world: World, bench: OpticalBench, directory: str | Path, seed: int | None = None,
                 stream: StreamConfig | Mapping[str, Any] | None = None,
                 trajectories: str | Path | None = None, render_delay: float = 0.0,
                 stamp_frames: bool = False) -> None:
        self.world = world
        self.bench = bench
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        seed = world.config.seed if seed is None else seed
        self.renderer = Renderer(bench, seed=seed, bit_depth=8, session=world.config.session)
        self.streams = StreamServer(world, bench, seed, self.directory / "streams",
                                    Path(trajectories) if trajectories is not None else None,
                                    stream if isinstance(stream, StreamConfig) else StreamConfig.from_dict(stream))
        self.paths = {name: self.directory / f"{name}.bmp" for name in AXIS_NAMES}
        self.laser_on = True
        self.exposure_scale = 1.0
        self.frames_written = 0
        self.announced = 0  # frame sets whose pose had been announced (matched its announcement)
        self.rendered_ahead = 0  # ... of which the rendering had started before the settled state came
        self._subscribed = False
        self._lock = threading.Lock()  # one frame set at a time is put in place
        self._render_lock = threading.Lock()  # the renderer's caches are not shared between threads
        self._ahead = threading.Condition()
        self._ahead_frames: _AheadFrames | None = None  # the latest announcement's
        self._announcements = 0
        self._worker: threading.Thread | None = None
        self._stopping = False
        self._last_state: WorldState | None = None
        self.render_delay = float(render_delay)
        self._delayed_sets = -1  # how many more settled frame sets wait render_delay (-1: all of them)
        self.stamp_frames = bool(stamp_frames)

    # ------------------------------------------------------------------ lifecycle (cell host API)
    def start(self) -> dict[str, Any]:
        """Render the current pose, then follow the world. Returns the file paths."""
        if not self._subscribed:
            self._stopping = False
            self._worker = threading.Thread(target=self._render_ahead_loop, name="camera-render-ahead", daemon=True)
            self._worker.start()
            self.world.subscribe(self._on_state)
            self.world.on_announce(self._on_announce)
            self._subscribed = True
            self._on_state(self.world.state(), force=True)
            self.streams.start()
        return {"files": {name: str(path) for name, path in self.paths.items()}, "streams": str(self.streams.root)}

    def stop(self) -> None:
        self.streams.stop()
        if self._subscribed:
            self.world.unsubscribe(self._on_state)
            self.world.remove_announce_listener(self._on_announce)
            self._subscribed = False
        with self._ahead:
            self._stopping = True
            self._ahead.notify_all()
        if self._worker is not None:
            self._worker.join(10.0)
            self._worker = None
        with self._ahead:
            if self._ahead_frames is not None:
                _remove(self._ahead_frames)
                self._ahead_frames = None

    def set_laser(self, on: bool) -> dict[str, int]:
        """Switch the OPR's lasers (off: the screens show only the background) and re-render now."""
        self.laser_on = bool(on)
        return self.render()

    def set_exposure(self, scale: float) -> dict[str, int]:
        """Scale the rendered signal (1: nominal) and re-render now."""
        self.exposure_scale = float(scale)
        return self.render()

    def render(self) -> dict[str, int]:
        """Render the current pose now, settled or not."""
        self._on_state(self.world.state(), force=True)
        return {"frames_written": self.frames_written}

    def set_render_delay(self, seconds: float, count: int = -1) -> dict[str, float]:
        """Starve the renderer: the next ``count`` settled frame sets (-1: every one) are put in place
        ``seconds`` late (a camera process that cannot keep up; the fault matrix's starved camera)."""
        if not seconds >= 0 or count < -1:
            raise ValueError(f"camera twin: render_delay needs seconds ≥ 0 and count ≥ -1, got {seconds}, {count}")
        self.render_delay, self._delayed_sets = float(seconds), int(count)
        return {"seconds": self.render_delay, "count": self._delayed_sets}

    def files(self) -> dict[str, str]:
        return {name: str(path) for name, path in self.paths.items()}

    def stats(self) -> dict[str, int]:
        """Frame sets written, how many had been announced, and how many of those were (being) rendered
        before their settled state came."""
        return {"frames_written": self.frames_written, "announced": self.announced,
                "rendered_ahead": self.rendered_ahead}

    def control(self, command: str, /, **kwargs: Any) -> Any:
        """``laser`` (on: bool), ``exposure`` (scale: float), ``render`` (re-render now), ``render_delay``
        (seconds, count: a starved renderer), ``files``, ``stats``,
        ``stream_stats`` (streams served, frames rendered, the cameras' clocks)."""
        commands: dict[str, Callable[..., Any]] = {"laser": self.set_laser, "exposure": self.set_exposure,
                                                   "render": self.render, "render_delay": self.set_render_delay,
                                                   "files": self.files, "stats": self.stats,
                                                   "stream_stats": self.streams.stats}
        return dispatch(commands, command, kwargs, "camera twin")

    # ------------------------------------------------------------------ rendering
    def _scale(self) -> float:
        return self.exposure_scale if self.laser_on else 0.0

    def _on_announce(self, expected: WorldState) -> None:
        """A pose is expected to settle next: queue its frames for the worker (returns at once)."""
        with self._ahead:
            previous = self._ahead_frames
            if previous is not None and previous.state in ("wanted", "done"):
                _remove(previous)  # superseded (one being rendered is removed by the worker)
            self._announcements += 1
            self._ahead_frames = _AheadFrames(
                self.frames_written + 1, expected.opr_in_m.copy(), self._scale(),
                {name: self.directory / f".{name}.ahead-{self._announcements}.bmp" for name in AXIS_NAMES})
            self._ahead.notify_all()

    def _render_ahead_loop(self) -> None:
        while True:
            with self._ahead:
                while not self._stopping and (self._ahead_frames is None or self._ahead_frames.state != "wanted"):
                    self._ahead.wait()
                if self._stopping:
                    return
                frames = self._ahead_frames
                assert frames is not None
                frames.state = "rendering"
            try:
                with self._render_lock:
                    for name, path in frames.paths.items():
                        image = self.renderer.render(name, frames.opr_in_m, seq=frames.index,
                                                     exposure_scale=frames.scale)
                        write_bmp_atomically(path, image)
                outcome = "done"
            except Exception:  # rendering ahead is an optimisation: the settled state renders anyway
                outcome = "failed"
            with self._ahead:
                frames.state = outcome
                if self._ahead_frames is not frames or outcome == "failed":
                    _remove(frames)  # superseded meanwhile
                self._ahead.notify_all()

    def _take_ahead(self, index: int, opr_in_m: np.ndarray, scale: float) -> tuple[bool, _AheadFrames | None]:
        """Whether this frame set was announced, and its frames if they were rendered ahead (waiting for
        them if under way; one not started yet is taken over: rendered here, now, at the same cost)."""
        with self._ahead:
            frames = self._ahead_frames
            # The same pose, computed in another process (the BLAS kernel may round the last bit
            # differently): 1e-12 m or rad is far below anything a pixel can show.
            if frames is None or frames.index != index or frames.scale != scale or not np.allclose(
                    frames.opr_in_m, opr_in_m, rtol=0.0, atol=1e-12):
                return False, None
            if frames.state == "wanted":
                frames.state = "taken"
                self._ahead_frames = None
                return True, None
            while frames.state == "rendering":
                self._ahead.wait(1.0)
            self._ahead_frames = None
            return True, frames if frames.state == "done" else None

    def _on_state(self, state: WorldState, force: bool = False) -> None:
        if not state.settled and not force:
            return  # frames keep showing the last settled pose while the robot moves
        with self._lock:
            index = self.frames_written + 1
            scale = self._scale()
            announced, ahead = self._take_ahead(index, state.opr_in_m, scale)
            if self.render_delay > 0 and self._delayed_sets != 0:
                time.sleep(self.render_delay)  # a slow renderer: the settled pose's ack comes this much later
                self._delayed_sets -= self._delayed_sets > 0
            still_since = time.time()  # the scene these frames show has been still at least since now
            files = {}
            for name in AXIS_NAMES:
                if ahead is not None and self.stamp_frames:
                    write_atomically(self.paths[name], stamp_bmp_file(ahead.paths[name], index, still_since))
                    ahead.paths[name].unlink(missing_ok=True)
                elif ahead is not None:
                    os.replace(ahead.paths[name], self.paths[name])  # atomic: the old frame or the new one
                else:
                    with self._render_lock:
                        image = self.renderer.render(name, state.opr_in_m, seq=index, exposure_scale=scale)
                    if self.stamp_frames:
                        stamp_image(image, index, still_since)
                    write_bmp_atomically(self.paths[name], image)
                files[name] = str(self.paths[name])
            self.frames_written = index
            self.announced += announced
            self.rendered_ahead += ahead is not None
            self._last_state = state
            self.world.truth.record(
                "frames", seq=state.seq, index=index, time=self.world.clock(), files=files,
                opr_in_m=pose_record(state.opr_in_m), laser_on=self.laser_on, rendered_ahead=ahead is not None,
                still_since=still_since if self.stamp_frames else None,
            )


def _remove(frames: _AheadFrames) -> None:
    for path in frames.paths.values():
        path.unlink(missing_ok=True)


class SimCamera:
    """An in-process camera implementing ``drivers.camera.Camera`` by rendering the world directly.

    Parameters
    ----------
    world, bench :
        The truth to image.
    name : "x", "y" or "z"
        Which screen's camera.
    bit_depth : 8 or 12
    faults : FaultPlan, optional
        ``DROP_REPLY`` → the next grab's buffer is incomplete (``GrabFailed`` after retries),
        ``STALL`` → no frame (``DeviceTimeout``), ``DISCONNECT`` → the camera vanished.
    retries : int
        Extra attempts after an incomplete buffer or a timeout.
    """

    def __init__(self, world: World, bench: OpticalBench, name: str, *, bit_depth: int = 8,
                 faults: FaultPlan | None = None, retries: int = 2, seed: int | None = None) -> None:
        if name not in AXIS_NAMES:
            raise ValueError(f"SimCamera name must be one of {AXIS_NAMES}, got {name!r}")
        self.name = name
        self.world = world
        self.bench = bench
        self.faults = faults or FaultPlan()
        self.retries = int(retries)
        self.renderer = Renderer(bench, seed=(world.config.seed if seed is None else seed) + 7919, bit_depth=bit_depth)
        self.exposure_scale = 1.0
        self.software_trigger = True
        self.roi: Roi | None = None
        self._open = False
        self._frame_id = 0
        self._pending: tuple[np.ndarray, float] | None = None
        self._device = f"camera {name} (sim)"

    # ------------------------------------------------------------------ Camera protocol
    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False
        self._pending = None

    def __enter__(self) -> SimCamera:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def configure(self, *, exposure_s: float | None = None, gain_db: float | None = None,
                  pixel_format: str | None = None, roi: Roi | None = None,
                  software_trigger: bool | None = None) -> None:
        """Exposure scales the rendered signal relative to 1 ms; gain in dB scales it too."""
        if exposure_s is not None:
            if exposure_s <= 0:
                raise ValueError(f"exposure_s must be positive, got {exposure_s}")
            self.exposure_scale = exposure_s / 1e-3
        if gain_db is not None:
            self.exposure_scale *= 10 ** (gain_db / 20.0)
        if pixel_format is not None:
            depth = {"Mono8": 8, "Mono12": 12}.get(pixel_format)
            if depth is None:
                raise ValueError(f"SimCamera supports pixel formats Mono8 and Mono12, got {pixel_format!r}")
            self.renderer = Renderer(self.bench, seed=self.renderer.seed, bit_depth=depth)
        if roi is not None:
            self.roi = roi
        if software_trigger is not None:
            self.software_trigger = bool(software_trigger)

    def trigger(self) -> None:
        """Expose now: the frame shows the world's pose at this instant."""
        self._require_open("trigger")
        state = self.world.state()
        self._pending = (state.opr_in_m, time.time())  # the pose at this instant, and the instant

    def retrieve(self, timeout: float = 2.0) -> Frame:
        """The frame of the last trigger (one attempt; ``grab`` adds retries)."""
        self._require_open("retrieve frame")
        if self.faults.take(FaultKind.DISCONNECT):
            self._open = False
            raise DeviceConnectionError(self._device, "retrieve frame", "the camera was removed")
        if self.faults.take(FaultKind.STALL) or self._pending is None:
            self._pending = None
            time.sleep(min(timeout, 0.01))
            raise DeviceTimeout(self._device, "retrieve frame", f"no frame within {timeout:.3g} s")
        opr_in_m, exposed_at = self._pending
        self._pending = None
        if self.faults.take(FaultKind.DROP_REPLY):
            raise GrabFailed(self._device, "retrieve frame", "the buffer was incompletely grabbed")
        self._frame_id += 1
        image = self.renderer.render(self.name, opr_in_m, seq=self._frame_id, exposure_scale=self.exposure_scale)
        if self.roi is not None:
            r = self.roi
            image = image[r.offset_y:r.offset_y + r.height, r.offset_x:r.offset_x + r.width].copy()
        return Frame(image, time.time(), self._frame_id, self.name, self.renderer.saturation, exposed_at, "exposure")

    def grab(self, timeout: float = 2.0) -> Frame:
        """Trigger and retrieve, retrying incomplete buffers and timeouts a bounded number of times."""
        last: GrabFailed | DeviceTimeout | None = None
        for _attempt in range(self.retries + 1):
            self.trigger()
            try:
                return self.retrieve(timeout)
            except (GrabFailed, DeviceTimeout) as error:
                last = error
        assert last is not None
        raise type(last)(self._device, "grab", f"{last.cause} ({self.retries + 1} attempts)")

    def _require_open(self, operation: str) -> None:
        if not self._open:
            raise DeviceConnectionError(self._device, operation, "the camera is not open (call open() first)")


__all__ = ["CameraFileTwin", "SimCamera", "write_bmp_atomically"]
