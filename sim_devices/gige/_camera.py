"""``GigeCameraTwin``: one GigE Vision camera of the sensor module, served on its own loopback address.

It answers GVCP on ``host``:3956 (``_control``; its own codec, ``_wire``; its own GenICam XML,
``_features``),
exposes when triggered — software (``TriggerSoftware``), a hardware line (``Line0``/``Line1``, driven
by ``line_pulses``: the cell's trigger generator), an action command (``Action1``: ACTION_CMD with
the device key, group key and mask the host set), or free-running at ``AcquisitionFrameRate`` — and
streams every frame LIVE over GVSP: rendered at the true OPR pose of its exposure (motion blur over
the exposure, ``sim_devices.camera.exposure_poses``) as soon as the robot's truth of that instant
is written, stamped on the camera's own clock (offset, drift, jitter; 1 GHz ticks, the exposure
start), with 16-bit block ids from 1.

Timing as a sensor has it: after a trigger the camera is busy for max(exposure, rows · line_time)
+ frame_overhead; a trigger meanwhile is missed (counted, nothing sent). Frames wait in the
camera's memory (``frame_buffers``) until rendered and sent; beyond that they are lost (counted).

Control (``control(command, **kwargs)``, the cell's channel): ``stats``, ``frames`` (the last frames'
truth: block id, exposure start on the controller clock, exposure, ticks, noise seq, roi, pixel
format, true OPR pose), ``clock`` (true offset and drift), ``line_pulses`` (t0, rate_hz, count),
``line_stop``, and the faults ``drop_packets`` (fraction, count, seed), ``unresponsive`` (seconds;
None: until cleared), ``late_trigger`` (delay, count: the exposure starts late), ``late_frames``
(delay, count: the frame is sent late), ``clear_faults``.
"""

from __future__ import annotations

import heapq
import ipaddress
import math
import queue
import threading
import time
import zlib
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from sim_devices._config import checked_fields
from sim_devices.camera import TICKS_PER_SECOND, CameraClock, OpticalBench, Renderer, exposure_poses
from sim_devices.control import dispatch
from sim_devices.gige import _features as f
from sim_devices.gige import _wire as w
from sim_devices.gige._channel import StreamChannel
from sim_devices.gige._control import ControlChannel
from sim_devices.gige._registers import RegisterError, RegisterSpace
from sim_devices.trajectory import TrajectoryLog
from sim_devices.world import World, pose_record

SEQ_BASE = 1 << 44  # noise seeds of GigE frames: apart from the file twin's frame sets and streams
POLL = 0.05  # s: the longest the trigger timing thread sleeps


@dataclass
class GigeTwinConfig:
    """One twin camera's identity, transport and timing (a cell's ``gige`` section per camera).

    Attributes
    ----------
    camera : "x", "y" or "z"
        Which screen this camera images.
    vendor, model, serial, version : str
        Identity registers; ``serial`` defaults to ``OPR-GV-<camera>``.
    heartbeat_timeout : float
        s without a GVCP command from the controlling host before the camera drops it (and stops).
    line_time, frame_overhead : float
        s per sensor row read out, and between frames beyond exposure or readout.
    clock_drift_std, timestamp_jitter : float
        The camera clock's rate error (σ, seeded) and stamp noise σ (s).
    blur_step_px, max_blur_samples :
        Motion blur: most motion between sub-poses, most sub-poses.
    truth_margin : float
        s the robot's truth of an instant may be written after it when no move is being recorded.
    truth_wait : float
        Longest s a frame waits for the truth of its exposure before it is rendered with what is known.
    frame_buffers : int
        Frames the camera holds before they are sent.
    resend_blocks : int
        Blocks kept for packet resend.
    render : "pose" or "static"
        ``static`` renders one frame per setting and sends it for every trigger (transport benchmarks).
    truth_log : bool
        Also write every frame's truth to the world's truth log.
    """

    camera: str = "x"
    vendor: str = "OPR Lab"
    model: str = "ScreenCam GV"
    serial: str = ""
    version: str = "1.0.0"
    heartbeat_timeout: float = 3.0
    line_time: float = 4.8e-6
    frame_overhead: float = 50e-6
    clock_drift_std: float = 20e-6
    timestamp_jitter: float = 1e-6
    blur_step_px: float = 0.25
    max_blur_samples: int = 12
    truth_margin: float = 0.05
    truth_wait: float = 5.0
    frame_buffers: int = 256
    resend_blocks: int = 16
    render: str = "pose"
    truth_log: bool = False

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> GigeTwinConfig:
        config = cls(**checked_fields(cls, data, "gige camera config"))
        if config.camera not in ("x", "y", "z"):
            raise ValueError(f"gige camera config: camera must be x, y or z, got {config.camera!r}")
        if config.render not in ("pose", "static"):
            raise ValueError(f"gige camera config: render must be 'pose' or 'static', got {config.render!r}")
        if min(config.line_time, config.frame_overhead, config.clock_drift_std, config.timestamp_jitter,
               config.truth_margin, config.truth_wait) < 0 or config.heartbeat_timeout <= 0 \
                or config.frame_buffers < 1 or config.resend_blocks < 1:
            raise ValueError("gige camera config: timings must be ≥ 0, heartbeat_timeout > 0, buffers ≥ 1")
        return config

    def to_dict(self) -> dict[str, Any]:
        return {field.name: getattr(self, field.name) for field in fields(self)}


@dataclass(frozen=True)
class _Exposure:
    number: int  # running count of this camera's exposures (the noise seed)
    block_id: int
    start: float  # controller clock, s
    exposure: float
    roi: tuple[int, int, int, int]
    pixel_format: str
    gain_db: float
    source: str


def check_loopback(host: str, allow_remote: bool) -> None:
    """Refuse an address outside 127.0.0.0/8 unless the caller says so explicitly."""
    if not allow_remote and not ipaddress.IPv4Address(host).is_loopback:
        raise ValueError(f"gige twin: {host} is not a loopback address (pass allow_remote=True to serve it)")


class GigeCameraTwin:
    """One twin camera (see the module docstring).

    Parameters
    ----------
    world : World
        The truth: the OPR's pose (rest, or the robot's dense truth through ``trajectories``).
    bench : OpticalBench
        The optics the frames are rendered through.
    host : str
        The camera's address (loopback unless ``allow_remote``); GVCP binds UDP 3956 on it.
    config : GigeTwinConfig or mapping, optional
    trajectories : path, optional
        The robot's dense truth (``sim_devices.trajectory``) and the controller clock's origin.
    """

    def __init__(self, world: World, bench: OpticalBench, host: str,
                 config: GigeTwinConfig | Mapping[str, Any] | None = None, *,
                 trajectories: str | Path | None = None, allow_remote: bool = False) -> None:
        check_loopback(host, allow_remote)
        self.world = world
        self.bench = bench
        self.host = host
        self.config = config if isinstance(config, GigeTwinConfig) else GigeTwinConfig.from_dict(config)
        self.name = self.config.camera
        serial = self.config.serial or f"OPR-GV-{self.name}"
        mac = bytes([0x02, 0x4F, 0x50]) + zlib.crc32(f"{host}/{serial}".encode()).to_bytes(4, "big")[1:]
        self.registers = RegisterSpace(host, self.config.vendor, self.config.model, serial, self.config.version, mac)
        self.truth = TrajectoryLog(Path(trajectories)) if trajectories is not None else None
        rng = world.rng(f"gige-clock-{self.name}")
        self.clock = CameraClock(float(rng.uniform(10.0, 1000.0)), float(rng.normal(0.0, self.config.clock_drift_std)),
                                 self.config.timestamp_jitter)
        self._stamp_rng = world.rng(f"gige-stamps-{self.name}")
        self._renderers: dict[int, Renderer] = {}
        self._static: dict[tuple[Any, ...], bytes] = {}
        self._own_origin = time.monotonic()
        self._origin = self._own_origin
        self._origin_checked = -math.inf
        self._known: tuple[float, float] = (-math.inf, 0.0)  # (truth written up to, when read)
        self._lock = threading.RLock()
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._jobs: queue.Queue[_Exposure | None] = queue.Queue()
        self._threads: list[threading.Thread] = []
        self.gvcp: ControlChannel | None = None
        self.channel: StreamChannel | None = None
        self._acquiring = False
        self._ready_at = -math.inf
        self._next_free_run = math.inf
        self._block_id = 0
        self._exposures = 0
        self._pulses: dict[str, Any] | None = None
        self._scheduled: list[tuple[float, str]] = []  # (controller time, source) of scheduled actions
        self._unresponsive_until = -math.inf
        self._late: tuple[float, int] = (0.0, 0)
        self._late_frames: tuple[float, int] = (0.0, 0)
        self._recent: deque[dict[str, Any]] = deque(maxlen=2000)
        self.counts = {"triggers": 0, "exposed": 0, "missed": 0, "overflow": 0, "sent": 0, "ignored": 0,
                       "truth_late": 0, "discarded": 0}
        self._init_features()

    # ------------------------------------------------------------------ features
    def _init_features(self) -> None:
        r = self.registers
        width, height = self.bench.cameras[self.name].size_px
        self.sensor = (int(width), int(height))
        for feature, value in (("SensorWidth", width), ("SensorHeight", height), ("WidthMax", width),
                               ("HeightMax", height), ("Width", width), ("Height", height), ("OffsetX", 0),
                               ("OffsetY", 0), ("PixelFormat", f.PIXEL_FORMATS["Mono8"]), ("ActionSelector", 1),
                               ("TriggerMode", f.TRIGGER_MODES["Off"]), ("GevSCPD", 0)):
            r.set(f.FEATURE[feature].address, int(value))
        for name, number in (("ExposureTime", 1000.0), ("Gain", 0.0), ("AcquisitionFrameRate", 10.0),
                             ("TriggerDelay", 0.0)):
            r.set_float(f.FEATURE[name].address, number)
        r.set_u64(f.TICK_FREQUENCY_HIGH, TICKS_PER_SECOND)
        self._update_payload()
        for name in ("Width", "Height", "OffsetX", "OffsetY"):
            r.watch(f.FEATURE[name].address, partial(self._set_roi, name))
        r.watch(f.FEATURE["PixelFormat"].address, self._set_pixel_format)
        for name, entries in (("AcquisitionMode", f.ACQUISITION_MODES), ("TriggerSelector", f.TRIGGER_SELECTORS),
                              ("TriggerMode", f.TRIGGER_MODES), ("TriggerSource", f.TRIGGER_SOURCES),
                              ("TriggerActivation", f.TRIGGER_ACTIVATIONS)):
            r.watch(f.FEATURE[name].address, partial(self._check_entry, name, entries))
        r.watch(f.FEATURE["AcquisitionStart"].address, lambda value: self._acquisition(True))
        r.watch(f.FEATURE["AcquisitionStop"].address, lambda value: self._acquisition(False))
        r.watch(f.FEATURE["TriggerSoftware"].address, lambda value: self._software_trigger())
        for name in ("ExposureTime", "Gain", "AcquisitionFrameRate", "TriggerDelay"):
            r.watch(f.FEATURE[name].address, partial(self._check_float, name))
        r.watch(f.TIMESTAMP_CONTROL, self._timestamp_control)
        r.watch(f.STREAM_PACKET_SIZE, self._check_packet_size)
        r.watch(f.HEARTBEAT_TIMEOUT, self._check_heartbeat)

    def _update_payload(self) -> None:
        ox, oy, width, height = self.roi()
        self.registers.set(f.FEATURE["PayloadSize"].address, width * height * f.BYTES_PER_PIXEL[self.pixel_format()])

    def roi(self) -> tuple[int, int, int, int]:
        r = self.registers
        return (r.get(f.FEATURE["OffsetX"].address), r.get(f.FEATURE["OffsetY"].address),
                r.get(f.FEATURE["Width"].address), r.get(f.FEATURE["Height"].address))

    def pixel_format(self) -> str:
        code = self.registers.get(f.FEATURE["PixelFormat"].address)
        return next(name for name, value in f.PIXEL_FORMATS.items() if value == code)

    def _entry(self, name: str, entries: Mapping[str, int]) -> str:
        code = self.registers.get(f.FEATURE[name].address)
        return next(k for k, v in entries.items() if v == code)

    def _float(self, name: str) -> float:
        return self.registers.get_float(f.FEATURE[name].address)

    def _refuse_while_acquiring(self, name: str) -> None:
        if self._acquiring:
            raise RegisterError(w.STATUS_ACCESS_DENIED, f"{name} cannot change while acquiring")

    def _set_roi(self, name: str, value: int) -> None:
        self._refuse_while_acquiring(name)
        ox, oy, width, height = self.roi()
        sensor_w, sensor_h = self.sensor
        feature = f.FEATURE[name]
        if value % int(feature.increment or 1) or value < int(feature.minimum or 0) \
                or ox + width > sensor_w or oy + height > sensor_h:
            raise RegisterError(w.STATUS_INVALID_PARAMETER, f"{name} = {value} does not fit the sensor")
        self._update_payload()

    def _set_pixel_format(self, value: int) -> None:
        self._refuse_while_acquiring("PixelFormat")
        if value not in f.PIXEL_FORMATS.values():
            raise RegisterError(w.STATUS_INVALID_PARAMETER, f"pixel format 0x{value:08x} is not served")
        self._update_payload()

    @staticmethod
    def _check_entry(name: str, entries: Mapping[str, int], value: int) -> None:
        if value not in entries.values():
            raise RegisterError(w.STATUS_INVALID_PARAMETER, f"{name}: no entry with value {value}")

    def _check_float(self, name: str, _raw: int) -> None:
        feature = f.FEATURE[name]
        value = self._float(name)
        if not (float(feature.minimum or 0.0) <= value <= float(feature.maximum or math.inf)):
            raise RegisterError(w.STATUS_INVALID_PARAMETER, f"{name} = {value:g} is out of range")

    def _check_packet_size(self, value: int) -> None:
        size = value & 0xFFFF
        feature = f.FEATURE["GevSCPSPacketSize"]
        if not int(feature.minimum or 0) <= size <= int(feature.maximum or 0) or size % 4:
            raise RegisterError(w.STATUS_INVALID_PARAMETER, f"packet size {size} is not served")

    @staticmethod
    def _check_heartbeat(value: int) -> None:
        if value < 500:
            raise RegisterError(w.STATUS_INVALID_PARAMETER, f"heartbeat timeout {value} ms is below 500 ms")

    def _timestamp_control(self, value: int) -> None:
        if value & f.TIMESTAMP_RESET:  # the clock restarts from 0 now
            now = self.controller_now()
            self.clock = CameraClock(-(1.0 + self.clock.drift) * now, self.clock.drift, self.clock.jitter)
        if value & f.TIMESTAMP_LATCH:
            self.registers.set_u64(f.TIMESTAMP_LATCHED_HIGH, self.clock.ticks(self.controller_now(), self._stamp_rng))

    # ------------------------------------------------------------------ clocks and truth
    def controller_now(self) -> float:
        """The robot controller's clock now (its origin from the robot twin; this twin's start without one)."""
        now = time.monotonic()
        if self.truth is not None and now > self._origin_checked + 1.0:  # a file read: not at every call
            clock = self.truth.clock()
            self._origin = float(clock["monotonic_origin"]) if clock else self._own_origin
            self._origin_checked = now
        return now - self._origin

    def opr_at(self, times: np.ndarray) -> np.ndarray:
        """True OPR poses in M (n, 4, 4) at controller ``times``."""
        state = self.world.state()
        if self.truth is None or state.mount != "robot":
            return np.repeat(state.opr_in_m[None], len(times), axis=0)
        flange = self.truth.flange_at(times, rest=self.world.reference_flange_pose)
        return np.linalg.inv(self.world.base_to_m)[None] @ flange @ self.world.true_opr_mount[None]

    def _truth_known(self, until: float) -> bool:
        if self.truth is None:
            return True
        if self._known[0] >= until:
            return True  # known that far already: no need to read the records again
        known = self.truth.known_until()
        self._known = (known if not math.isinf(known) else -math.inf, time.monotonic())
        if math.isinf(known):  # no move is being recorded: the robot rests, unless one starts right now
            return self.controller_now() - self.config.truth_margin >= until
        return known >= until

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> dict[str, Any]:
        """Bind GVCP (``host``:3956) and the stream source; start serving. Returns the endpoints."""
        self.gvcp = ControlChannel(self.host, self.registers, on_resend=self._resend, on_action=self._action,
                                   on_control_lost=self._control_lost, unresponsive=self._unresponsive)
        self.channel = StreamChannel(self.host, self.config.resend_blocks)
        self.registers.set(f.STREAM_SOURCE_PORT, self.channel.source_port)
        self._stopping.clear()
        self._renderer(8)  # its caches built now: the first triggered frame is as fast as the others
        self.gvcp.start(self.name)
        for target, label in ((self._time_triggers, "triggers"), (self._produce, "frames")):
            thread = threading.Thread(target=target, name=f"gige-{self.name}-{label}", daemon=True)
            thread.start()
            self._threads.append(thread)
        return self.endpoints()

    def endpoints(self) -> dict[str, Any]:
        return {"host": self.host, "port": w.GVCP_PORT, "camera": self.name,
                "serial": self.registers.read(f.SERIAL_NUMBER, 16).rstrip(b"\0").decode(),
                "device_id": self.device_id()}

    def device_id(self) -> str:
        """Aravis's id of this camera: ``vendor-model-serial`` (spaces are kept)."""
        serial = self.registers.read(f.SERIAL_NUMBER, 16).rstrip(b"\0").decode()
        return f"{self.config.vendor}-{self.config.model}-{serial}"

    def stop(self) -> None:
        self._stopping.set()
        self._wake.set()
        self._jobs.put(None)
        for thread in self._threads:
            thread.join(10.0)
        self._threads = []
        if self.gvcp is not None:
            self.gvcp.stop()
            self.gvcp = None
        if self.channel is not None:
            self.channel.close()

    def __enter__(self) -> GigeCameraTwin:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ GVCP
    def _unresponsive(self) -> bool:
        return time.monotonic() < self._unresponsive_until

    def _control_lost(self) -> None:
        """The controlling host is gone (heartbeat expired, released, or the camera lost it): stop."""
        with self._lock:
            self._acquiring = False
        self.registers.set(f.STREAM_PORT, 0)

    def _resend(self, block_id: int, first: int, last: int) -> None:
        if self.channel is not None:
            self.channel.resend(block_id, first, last, self._destination())

    def _action(self, flags: int, payload: bytes) -> None:
        """ACTION_CMD: trigger ``Action1`` if the keys are this camera's (at once, or at its action time)."""
        device_key, group_key, group_mask = (int.from_bytes(payload[i:i + 4], "big") for i in (0, 4, 8))
        r = self.registers
        if device_key != r.get(f.ACTION_DEVICE_KEY) or group_key != r.get(f.ACTION_GROUP_KEY) \
                or not group_mask & r.get(f.ACTION_GROUP_MASK):
            return
        when = self.controller_now()
        if flags & w.FLAG_ACTION_TIME and len(payload) >= 20:
            ticks = int.from_bytes(payload[12:20], "big")  # the camera's clock: back to the controller's
            when = max(when, (ticks / TICKS_PER_SECOND - self.clock.offset) / (1.0 + self.clock.drift))
            with self._lock:
                heapq.heappush(self._scheduled, (when, "Action1"))
            self._wake.set()
        else:
            self._trigger(when, "Action1")

    # ------------------------------------------------------------------ acquisition
    def _acquisition(self, on: bool) -> None:
        with self._lock:
            self._acquiring = on
            if on:
                self._next_free_run = self.controller_now()
        self._wake.set()

    def _software_trigger(self) -> None:
        self._trigger(self.controller_now(), "Software")

    def _trigger(self, when: float, source: str) -> None:
        """A trigger signal at controller time ``when`` from ``source``: expose if armed for it and idle."""
        with self._lock:
            self.counts["triggers"] += 1
            if not self._acquiring or self._entry("TriggerMode", f.TRIGGER_MODES) != ("On" if source != "FreeRun"
                                                                                       else "Off"):
                self.counts["ignored"] += 1
                return
            if source != "FreeRun" and self._entry("TriggerSource", f.TRIGGER_SOURCES) != source:
                self.counts["ignored"] += 1
                return
            late, count = self._late
            if count > 0:
                self._late = (late, count - 1)
            else:
                late = 0.0
            exposure = self._float("ExposureTime") * 1e-6
            start = when + self._float("TriggerDelay") * 1e-6 + late
            if start < self._ready_at - 1e-12:
                self.counts["missed"] += 1
                return
            roi = self.roi()
            self._ready_at = start + max(exposure, roi[3] * self.config.line_time) + self.config.frame_overhead
            if self._jobs.qsize() >= self.config.frame_buffers:
                self.counts["overflow"] += 1
                return
            self._block_id = w.next_block_id(self._block_id)
            self._exposures += 1
            self.counts["exposed"] += 1
            self._jobs.put(_Exposure(self._exposures, self._block_id, start, exposure, roi, self.pixel_format(),
                                     self._float("Gain"), source))
            if self._entry("AcquisitionMode", f.ACQUISITION_MODES) == "SingleFrame":
                self._acquiring = False

    def _time_triggers(self) -> None:
        """Free-running exposures, the line's pulses and scheduled actions, each at its own instant."""
        while not self._stopping.is_set():
            now = self.controller_now()
            events: list[tuple[float, str]] = []
            with self._lock:
                if self._acquiring and self._entry("TriggerMode", f.TRIGGER_MODES) == "Off":
                    events.append((self._next_free_run, "FreeRun"))
                pulses = self._pulses
                if pulses is not None and (pulses["count"] is None or pulses["fired"] < pulses["count"]):
                    events.append((pulses["t0"] + pulses["fired"] * pulses["period"], pulses["line"]))
                if self._scheduled:
                    events.append(self._scheduled[0])
            if not events:
                self._wake.wait(POLL)
                self._wake.clear()
                continue
            when, source = min(events)
            if when > now:
                self._wake.wait(min(POLL, when - now))
                self._wake.clear()
                continue
            with self._lock:
                if source == "FreeRun":
                    rate = self._float("AcquisitionFrameRate")
                    self._next_free_run = max(when + 1.0 / rate, now - 1.0 / rate)
                elif source == "Action1" and self._scheduled and self._scheduled[0] == (when, source):
                    heapq.heappop(self._scheduled)
                elif self._pulses is not None and source == self._pulses["line"]:
                    self._pulses["fired"] += 1
            if not self._unresponsive():
                # A line pulse or an action time is an instant of its own: the exposure starts then, however
                # late this thread wakes. A free-running sensor has no such instant: a late wake-up (a busy
                # host) exposes now, never in the past.
                self._trigger(max(when, self.controller_now()) if source == "FreeRun" else when, source)

    # ------------------------------------------------------------------ frames
    def _renderer(self, bit_depth: int) -> Renderer:
        """The renderer of ``bit_depth``, primed with one full frame: it builds its caches (background,
        noise pool; 0.1–1 s on a busy machine) then, and its background-noise pool is sized for the full
        sensor from the start, so a frame's noise depends on (seed, camera, seq) only, never on which
        ROIs were rendered before (the pool's size sets where a frame's noise window may start)."""
        if bit_depth not in self._renderers:
            renderer = Renderer(self.bench, seed=self.world.config.seed, bit_depth=bit_depth)
            renderer.render(self.name, self.world.state().opr_in_m, seq=0)
            self._renderers[bit_depth] = renderer
        return self._renderers[bit_depth]

    def _image(self, job: _Exposure) -> tuple[bytes, np.ndarray]:
        """The frame's bytes as the pixel format carries them, and the true OPR pose at its middle."""
        scale = job.exposure / 1e-3 * 10.0 ** (job.gain_db / 20.0)
        static_key = (job.roi, job.pixel_format, job.exposure, job.gain_db)
        if self.config.render == "static":
            middle = self.opr_at(np.array([job.start + 0.5 * job.exposure]))[0]
            if static_key not in self._static:
                self._static[static_key] = self._encode(job, middle, None, scale)
            return self._static[static_key], middle
        middle, blur = exposure_poses(self.bench, self.opr_at, job.start, job.exposure, self.config.blur_step_px,
                                      self.config.max_blur_samples)
        return self._encode(job, middle, blur, scale), middle

    def _encode(self, job: _Exposure, middle: np.ndarray, blur: list[np.ndarray] | None, scale: float) -> bytes:
        bit_depth = 8 if job.pixel_format == "Mono8" else 12
        image = self._renderer(bit_depth).render(self.name, middle, seq=SEQ_BASE + job.number, roi=job.roi,
                                                 blur=blur, exposure_scale=scale)
        return pixel_bytes(image, job.pixel_format)

    def _produce(self) -> None:
        """Render each exposure once the truth of it is written, and send it."""
        while not self._stopping.is_set():
            try:
                job = self._jobs.get(timeout=POLL)
            except queue.Empty:
                continue
            if job is None:
                return
            # A frame leaves the camera once it is exposed and read out, never before (a late trigger's
            # frame comes late), and once the truth of its exposure is written.
            read_out = job.start + job.exposure + job.roi[3] * self.config.line_time
            while self.controller_now() < read_out:
                if self._stopping.wait(min(POLL, max(0.0, read_out - self.controller_now()))):
                    return
            with self._lock:
                held, count = self._late_frames
                self._late_frames = (held, count - 1) if count > 0 else (0.0, 0)
            if count > 0 and self._stopping.wait(held):
                return
            deadline = time.monotonic() + self.config.truth_wait
            while not self._truth_known(job.start + job.exposure) and time.monotonic() < deadline:
                if self._stopping.wait(0.002):
                    return
            if not self._truth_known(job.start + job.exposure):
                self.counts["truth_late"] += 1
            data, middle = self._image(job)
            ticks = self.clock.ticks(job.start, self._stamp_rng)
            record = {"camera": self.name, "block_id": job.block_id, "number": job.number, "start": job.start,
                      "exposure": job.exposure, "ticks": ticks, "seq": SEQ_BASE + job.number, "roi": list(job.roi),
                      "pixel_format": job.pixel_format, "source": job.source, "opr_in_m": pose_record(middle)}
            self._recent.append(record)
            if self.config.truth_log:
                self.world.truth.record("gige_frame", **record)
            if self._unresponsive():
                self.counts["discarded"] += 1
                continue
            assert self.channel is not None
            self.channel.send_block(self._destination(), job.block_id, ticks, f.PIXEL_FORMATS[job.pixel_format],
                                    job.roi, data, self.registers.get(f.STREAM_PACKET_SIZE) & 0xFFFF)
            self.counts["sent"] += 1

    def _destination(self) -> tuple[str, int]:
        """Where the stream goes: ``GevSCDA``:``GevSCPHostPort`` (port 0: nowhere)."""
        return (str(ipaddress.IPv4Address(self.registers.get(f.STREAM_DESTINATION))),
                self.registers.get(f.STREAM_PORT) & 0xFFFF)

    # ------------------------------------------------------------------ control (tests, the cell)
    def control(self, command: str, /, **kwargs: Any) -> Any:
        commands: dict[str, Callable[..., Any]] = {
            "stats": self.stats, "frames": self.frames, "clock": self.clock_truth, "line_pulses": self.line_pulses,
            "line_stop": self.line_stop, "drop_packets": self.drop_packets, "unresponsive": self.unresponsive,
            "late_trigger": self.late_trigger, "late_frames": self.late_frames, "clear_faults": self.clear_faults,
            "endpoints": self.endpoints}
        return dispatch(commands, command, kwargs, "gige twin")

    def stats(self) -> dict[str, Any]:
        channel = self.channel.stats.__dict__ if self.channel is not None else {}
        gvcp = self.gvcp
        with self._lock:
            return {**self.counts, "acquiring": self._acquiring, "queued": self._jobs.qsize(), "channel": dict(channel),
                    "controller": gvcp is not None and gvcp.controller is not None,
                    "control_lost": 0 if gvcp is None else gvcp.control_lost,
                    "commands": 0 if gvcp is None else gvcp.commands}

    def frames(self, last: int = 100) -> list[dict[str, Any]]:
        """The truth of the last ``last`` frames rendered (oldest first)."""
        return list(self._recent)[-int(last):]

    def clock_truth(self) -> dict[str, float]:
        return {"offset": self.clock.offset, "drift": self.clock.drift, "tick_frequency": TICKS_PER_SECOND,
                "controller_now": self.controller_now()}

    def line_pulses(self, rate_hz: float, t0: float | None = None, count: int | None = None,
                    line: str = "Line0") -> dict[str, Any]:
        """Drive trigger line ``line`` at ``rate_hz`` from controller time ``t0`` (default now + 5 ms)."""
        if not 0 < rate_hz <= 10_000 or line not in ("Line0", "Line1"):
            raise ValueError(f"line pulses: rate must be in (0, 10 kHz] and line Line0 or Line1, got {rate_hz}, {line}")
        start = self.controller_now() + 0.005 if t0 is None else float(t0)
        with self._lock:
            self._pulses = {"t0": start, "period": 1.0 / rate_hz, "count": count, "fired": 0, "line": line}
        self._wake.set()
        return {"t0": start, "period": 1.0 / rate_hz}

    def line_stop(self) -> dict[str, Any]:
        """Stop the pulses; returns how many fired and when the first one was."""
        with self._lock:
            pulses, self._pulses = self._pulses, None
        return {"fired": 0} if pulses is None else {"fired": pulses["fired"], "t0": pulses["t0"],
                                                    "period": pulses["period"]}

    def drop_packets(self, fraction: float, count: int | None = None, seed: int = 0) -> None:
        assert self.channel is not None
        self.channel.drop(fraction, count, seed)

    def unresponsive(self, seconds: float | None = None) -> None:
        """Stop answering and streaming for ``seconds`` (None: until ``clear_faults``)."""
        self._unresponsive_until = math.inf if seconds is None else time.monotonic() + float(seconds)

    def late_trigger(self, delay: float, count: int = 1) -> None:
        """The next ``count`` triggers start their exposure ``delay`` s late."""
        self._late = (float(delay), int(count))

    def late_frames(self, delay: float, count: int = 1) -> None:
        """The next ``count`` frames leave the camera ``delay`` s after their readout (a congested link)."""
        with self._lock:
            self._late_frames = (float(delay), int(count))

    def clear_faults(self) -> None:
        self._unresponsive_until = -math.inf
        self._late = (0.0, 0)
        self._late_frames = (0.0, 0)
        if self.channel is not None:
            self.channel.drop(0.0)


def pixel_bytes(image: np.ndarray, pixel_format: str) -> bytes:
    """A rendered frame (uint8, or uint16 with 12 significant bits) as ``pixel_format`` carries it:
    Mono8 one byte a pixel; Mono12 the 12-bit values in little-endian 16-bit words; Mono16 those
    values scaled to the full 16 bits (the 12-bit range mapped onto 0…65535)."""
    if pixel_format == "Mono8":
        return np.ascontiguousarray(image, dtype=np.uint8).tobytes()
    if pixel_format == "Mono16":
        image = np.rint(image.astype(np.float64) * (65535.0 / 4095.0)).astype(np.uint16)
    return np.ascontiguousarray(image, dtype="<u2").tobytes()
