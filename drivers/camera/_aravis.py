"""``AravisCamera``: any GigE Vision camera through Aravis 0.8 (GObject introspection, PyGObject).

Settings (``AravisSettings``: a station file's camera entry with ``adapter: aravis``)
-----------------------------------------------------------------------------------
device / address : str
    Aravis's device id (``vendor-model-serial``, or the serial) or the camera's IPv4 address —
    exactly one. An address is opened directly (no discovery broadcast needed).
pixel_format : Mono8, Mono12 or Mono16
exposure_s, gain_db, roi :
    ``ExposureTime`` (µs on the camera; ``ExposureTimeAbs`` on older SFNC), ``Gain`` (dB),
    ``OffsetX``/``OffsetY``/``Width``/``Height``.
trigger_source : Software (default), Line0 … or Action1
    ``TriggerSelector FrameStart``, ``TriggerMode On``. Software: each grab fires
    ``TriggerSoftware``. A line: the grab waits for the externally triggered frame. Action1: the
    camera takes the ``action`` keys and a grab triggers its ``ActionGroup`` (one command for every
    camera of the group once all were triggered: ``CameraTriplet`` does it for three).
packet_size : int, optional
    ``GevSCPSPacketSize`` (bytes per stream datagram; 9000 with jumbo frames on the link).
packet_resend, packet_timeout_s, frame_retention_s, buffers :
    Aravis's stream: ask for lost packets again, how long to wait for one, how long to keep an
    incomplete frame, how many buffers are queued.
retries, timeout_s :
    Extra attempts after an incomplete frame or a timeout; default grab timeout.

Errors: a camera not found, gone or whose control was lost (heartbeat) → ``DeviceConnectionError``;
a frame that does not come → ``DeviceTimeout``; a frame that did not arrive whole → ``GrabFailed``.
Frames carry the camera's frame id and, in ``Frame.timestamp``, the host time the frame's first
packet arrived; ``stream_fetch`` gives the camera's own timestamp (exposure start, ns).

Aravis and PyGObject come from the operating system and PyPI (``.[aravis]``, ``.ci/run``); without
them ``aravis_available()`` says why and ``open()`` raises ``DeviceConnectionError`` saying so.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from drivers._errors import DeviceConnectionError, DeviceError, DeviceTimeout
from drivers.camera._aravis_action import ActionGroup
from drivers.camera._interface import Frame, GrabFailed, Roi
from drivers.camera._pylon import SATURATION
from drivers.camera._settings import AravisSettings

_POP_SLICE_US = 50_000  # one bounded wait inside a longer one: a lost camera is noticed within it
_DTYPES: dict[str, np.dtype[Any]] = {"Mono8": np.dtype(np.uint8), "Mono12": np.dtype("<u2"), "Mono16": np.dtype("<u2")}


def _aravis() -> tuple[Any, Any]:
    """(Aravis, GLib) imported lazily, so that importing ``drivers`` never needs them."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis, GLib
    except (ImportError, ValueError) as error:
        raise DeviceConnectionError("aravis", "import Aravis", f"Aravis 0.8 through PyGObject is not available "
                                    f"({error}); install the .[aravis] extra and the OS packages (.ci/run)") from None
    return Aravis, GLib


def aravis_available() -> str | None:
    """None if Aravis can be used here; else one line saying why not."""
    try:
        _aravis()
    except DeviceConnectionError as error:
        return error.cause
    return None


class AravisCamera:
    """One GigE Vision camera; see the module docstring for the settings."""

    def __init__(self, settings: AravisSettings, *, name: str | None = None) -> None:
        self.settings = settings
        self.target = str(settings.address) if settings.address is not None else str(settings.device)
        self.serial = self.target
        self.name = name or self.target
        self.retries = settings.retries
        self.timeout_s = settings.timeout_s
        self.trigger_source: str | None = settings.trigger_source
        self._device = f"camera {self.name} ({self.target})"
        self._settings: dict[str, Any] = {"exposure_s": settings.exposure_s, "gain_db": settings.gain_db,
                                          "pixel_format": settings.pixel_format, "roi": settings.roi}
        self._camera: Any = None
        self._stream: Any = None
        self._payload = 0
        self._control_lost = threading.Event()
        self._address: str | None = None
        self._group: ActionGroup | None = None
        self._stream_saved: dict[str, Any] | None = None
        self._cleared: Any = None
        self.stray_buffers = 0  # buffers put back unread: unfilled, or exposed before the last trigger (_pop)
        self._can_latch = False
        self._tick_frequency = 1e9
        self._not_before_ns = 0
        self._latched_at: float | None = None  # host wall-clock time of the last latch (_not_before_ns)

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        if self._camera is not None:
            return
        aravis, glib = _aravis()
        try:
            camera = aravis.Camera.new(self.target)
        except glib.Error as error:
            raise DeviceConnectionError(self._device, "open", error.message) from None
        if camera is None:
            raise DeviceConnectionError(self._device, "open", f"no GigE Vision camera answers as {self.target}")
        self._camera = camera
        self._cleared = aravis.BufferStatus.CLEARED
        self._control_lost.clear()
        try:
            device = camera.get_device()
            device.connect("control-lost", lambda *_: self._control_lost.set())
            self.serial = camera.get_device_serial_number() or self.target
            self._address = self._device_address(device)
            if self.settings.packet_size is not None:
                self._set_integer("GevSCPSPacketSize", self.settings.packet_size)
            self._can_latch = all(self._has(feature) for feature in (
                "GevTimestampControlLatch", "GevTimestampValue", "GevTimestampTickFrequency"))
            if self._can_latch:
                self._tick_frequency = float(self._call("read the tick frequency", "get_integer",
                                                        "GevTimestampTickFrequency")) or 1e9
            self._apply(self._settings)
            self._arm(self.trigger_source)
            self._start()
        except BaseException:
            self.close()
            raise

    def _device_address(self, device: Any) -> str:
        """The camera's IPv4 address (where an action command goes)."""
        if self.settings.address is not None:
            return str(self.settings.address)
        socket_address = device.get_device_address()  # a GInetSocketAddress: address and GVCP port
        return str(socket_address.get_address().to_string())

    def close(self) -> None:
        camera, self._camera = self._camera, None
        if self._group is not None and self._address is not None:
            self._group.leave(self._address)
            self._group = None
        if camera is None:
            return
        _, glib = _aravis()
        try:
            camera.stop_acquisition()
        except glib.Error:
            pass  # a camera that is gone is as stopped as it gets
        self._stream = None
        del camera  # Aravis leaves control and ends its heartbeat when the last reference goes

    def __enter__(self) -> AravisCamera:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def is_open(self) -> bool:
        return self._camera is not None

    @property
    def emulated(self) -> bool:
        """Never pylon's file emulator: frames come live (``drivers.camera._stream``)."""
        return False

    # ------------------------------------------------------------------ features
    def _call(self, operation: str, function: Any, *args: Any) -> Any:
        camera = self._require_open(operation)
        _, glib = _aravis()
        try:
            return getattr(camera, function)(*args)
        except glib.Error as error:
            raise self._lost_or(DeviceError, operation, error.message) from None

    def _has(self, feature: str) -> bool:
        return bool(self._call(f"look up {feature}", "is_feature_available", feature))

    def _set_string(self, feature: str, value: str) -> None:
        self._call(f"set {feature} = {value}", "set_string", feature, value)

    def _set_integer(self, feature: str, value: int) -> None:
        self._call(f"set {feature} = {value}", "set_integer", feature, int(value))

    def _set_float_first(self, names: tuple[str, ...], value: float, what: str) -> None:
        for name in names:
            if self._has(name):
                self._call(f"set {name} = {value:g}", "set_float", name, float(value))
                return
        raise DeviceError(self._device, f"set {what}", f"the camera has none of {', '.join(names)}")

    def _apply(self, settings: Mapping[str, Any]) -> None:
        if settings.get("pixel_format") is not None:
            self._set_string("PixelFormat", settings["pixel_format"])
        if settings.get("roi") is not None:
            roi: Roi = settings["roi"]
            self._set_integer("OffsetX", 0)
            self._set_integer("OffsetY", 0)
            self._set_integer("Width", roi.width)
            self._set_integer("Height", roi.height)
            self._set_integer("OffsetX", roi.offset_x)
            self._set_integer("OffsetY", roi.offset_y)
        if settings.get("exposure_s") is not None:
            self._set_float_first(("ExposureTime", "ExposureTimeAbs"), float(settings["exposure_s"]) * 1e6, "exposure")
        if settings.get("gain_db") is not None:
            self._set_float_first(("Gain", "GainAbs"), float(settings["gain_db"]), "gain in dB")

    def _arm(self, source: str | None) -> None:
        """Frame start on ``source`` (None: free-running)."""
        if self._has("TriggerSelector"):
            self._set_string("TriggerSelector", "FrameStart")
        if source is None:
            self._set_string("TriggerMode", "Off")
            return
        self._set_string("TriggerMode", "On")
        self._set_string("TriggerSource", source)
        if source.startswith("Line") and self._has("TriggerActivation"):
            self._set_string("TriggerActivation", "RisingEdge")
        if source == "Action1":
            action = self.settings.action
            if action is None:
                raise DeviceError(self._device, "arm Action1", "trigger_source Action1 needs the action settings")
            self._set_integer("ActionDeviceKey", action.device_key)
            if self._has("ActionSelector"):
                self._set_integer("ActionSelector", 1)
            self._set_integer("ActionGroupKey", action.group_key)
            self._set_integer("ActionGroupMask", action.group_mask)
            if self._group is None and self._address is not None:
                self._group = ActionGroup.of(action.device_key, action.group_key, action.group_mask,
                                             None if action.broadcast is None else str(action.broadcast))
                self._group.join(self._address)

    def _start(self) -> None:
        """A fresh stream with its buffers, then acquisition."""
        aravis, glib = _aravis()
        camera = self._require_open("start acquisition")
        try:
            self._payload = int(camera.get_payload())
            stream = camera.create_stream(None, None)
            if stream is None:
                raise DeviceConnectionError(self._device, "create stream", "Aravis gave no stream")
            stream.set_property("packet-resend", aravis.GvStreamPacketResend.ALWAYS if self.settings.packet_resend
                                else aravis.GvStreamPacketResend.NEVER)
            stream.set_property("packet-timeout", int(self.settings.packet_timeout_s * 1e6))
            stream.set_property("frame-retention", int(self.settings.frame_retention_s * 1e6))
            for _ in range(self.settings.buffers):
                stream.push_buffer(aravis.Buffer.new_allocate(self._payload))
            self._stream = stream
            camera.start_acquisition()
        except glib.Error as error:
            raise self._lost_or(DeviceError, "start acquisition", error.message) from None

    def _stop(self) -> None:
        _, glib = _aravis()
        try:
            self._require_open("stop acquisition").stop_acquisition()
        except glib.Error as error:
            raise self._lost_or(DeviceError, "stop acquisition", error.message) from None
        self._stream = None

    def configure(self, *, exposure_s: float | None = None, gain_db: float | None = None,
                  pixel_format: str | None = None, roi: Roi | None = None,
                  software_trigger: bool | None = None) -> None:
        """Change settings; applied now when open (acquisition is stopped around the change)."""
        changes = {k: v for k, v in {"exposure_s": exposure_s, "gain_db": gain_db, "pixel_format": pixel_format,
                                     "roi": roi}.items() if v is not None}
        self._settings.update(changes)
        if software_trigger is not None:
            self.trigger_source = "Software" if software_trigger else None
        if self._camera is None:
            return
        self._stop()
        self._apply(changes)
        self._arm(self.trigger_source)
        self._start()

    # ------------------------------------------------------------------ grabbing
    def _fire(self) -> None:
        if self.trigger_source == "Software":
            self._call("trigger", "execute_command", "TriggerSoftware")
        elif self.trigger_source == "Action1" and self._group is not None and self._address is not None:
            self._group.ready(self._address, self._device)

    def _latch(self) -> None:
        """Note the camera's clock now: a frame stamped earlier was exposed before this call (a late
        frame of an earlier trigger, or one the camera still had queued) and is never handed out."""
        if not self._can_latch:
            return
        latched_at = time.time()  # the latch happens after this: a frame not before it is not before this
        self._call("latch the timestamp", "execute_command", "GevTimestampControlLatch")
        ticks = int(self._call("read the timestamp", "get_integer", "GevTimestampValue"))
        self._not_before_ns = int(ticks * 1e9 / self._tick_frequency)
        self._latched_at = latched_at

    def trigger(self) -> None:
        """Drop frames exposed before this call, then fire (software or action; a line fires itself)."""
        stream = self._require_stream("trigger")
        while True:
            stale = stream.try_pop_buffer()
            if stale is None:
                break
            stream.push_buffer(stale)
        self._latch()
        self._fire()

    def _pop(self, timeout: float) -> Any:
        """The next buffer within ``timeout`` s (in bounded slices, watching for a lost camera), or None."""
        stream = self._require_stream("retrieve frame")
        deadline = time.monotonic() + timeout
        while True:
            if self._control_lost.is_set():
                raise DeviceConnectionError(self._device, "retrieve frame", "control lost (the heartbeat failed)")
            left = deadline - time.monotonic()
            wait = int(max(0.0, min(left, _POP_SLICE_US / 1e6)) * 1e6)
            buffer = stream.timeout_pop_buffer(wait) if wait > 0 else stream.try_pop_buffer()
            if buffer is not None and (buffer.get_status() == self._cleared
                                       or int(buffer.get_timestamp()) < self._not_before_ns):
                # Aravis hands back a buffer it never filled when a stray datagram on the stream socket
                # started a block it could not size; and a frame exposed before the last trigger (or
                # the stream's start) may still come. Neither is this call's frame, nor a lost one.
                self.stray_buffers += 1
                stream.push_buffer(buffer)
                continue
            if buffer is not None or left <= 0:
                return buffer

    def _frame(self, buffer: Any) -> tuple[Frame | None, int, int, str | None]:
        """(frame or None, frame id, camera timestamp ns, why the buffer failed or None); re-queues it."""
        aravis, _ = _aravis()
        stream = self._require_stream("retrieve frame")
        try:
            frame_id = int(buffer.get_frame_id())
            stamp = int(buffer.get_timestamp())
            status = buffer.get_status()
            if status != aravis.BufferStatus.SUCCESS:
                return None, frame_id, stamp, f"buffer {status.value_nick} (frame {frame_id})"
            pixel_format = _format_name(int(buffer.get_image_pixel_format()))
            width, height = int(buffer.get_image_width()), int(buffer.get_image_height())
            data = np.frombuffer(buffer.get_data(), dtype=_DTYPES.get(pixel_format, np.dtype(np.uint8)))
            image = data[: width * height].reshape(height, width).astype(data.dtype.newbyteorder("="), copy=True)
            host = int(buffer.get_system_timestamp()) / 1e9
        finally:
            stream.push_buffer(buffer)
        # Only frames stamped at or after the latch are handed out (_pop): their exposure started after it.
        exposure = (self._latched_at, "exposure") if self._latched_at is not None else (None, None)
        frame = Frame(image, host, frame_id, self.serial, SATURATION.get(pixel_format, int(image.max())), *exposure)
        return frame, frame_id, stamp, None

    def retrieve(self, timeout: float | None = None) -> Frame:
        """The next frame (one attempt, no retry)."""
        timeout = self.timeout_s if timeout is None else float(timeout)
        buffer = self._pop(timeout)
        if buffer is None:
            raise DeviceTimeout(self._device, "retrieve frame", f"no frame within {timeout:.3g} s")
        frame, frame_id, _, failure = self._frame(buffer)
        if frame is None:
            raise GrabFailed(self._device, "retrieve frame", failure or "incomplete frame")
        return frame

    def grab(self, timeout: float | None = None) -> Frame:
        """Trigger and retrieve one frame; incomplete frames and timeouts are retried ``retries``
        times before the typed error is raised. A lost camera is not retried."""
        last: DeviceError | None = None
        for _attempt in range(self.retries + 1):
            try:
                self.trigger()
                return self.retrieve(timeout)
            except (GrabFailed, DeviceTimeout) as error:
                last = error
        assert last is not None
        raise type(last)(self._device, "grab", f"{last.cause} (after {self.retries + 1} attempts)")

    # ------------------------------------------------------------------ streaming (drivers.camera._stream)
    def stream_begin(self, *, exposure_s: float | None, roi: Roi | None, trigger_source: str,
                     sequence: object = None) -> float:
        """Re-arm for a stream: ROI, exposure, frame start on ``trigger_source``. Returns the tick
        frequency of ``stream_fetch``'s stamps (Aravis gives them in ns). ``stream_end`` undoes it."""
        self._stop()
        if self._stream_saved is None:
            self._stream_saved = {"roi": self._current_roi(), "trigger_source": self.trigger_source}
        if self.trigger_source == "Action1" and trigger_source == "Software":
            trigger_source = "Action1"  # software-paced triggers go out as the group's action
        self._apply({"roi": roi, "exposure_s": exposure_s})
        self.trigger_source = trigger_source
        self._arm(trigger_source)
        self._start()
        self._latch()  # frames the camera exposed before (still queued, or late) are not the stream's
        return 1e9

    def stream_fire(self) -> None:
        """One trigger, nothing drained: every frame of a stream is wanted."""
        self._require_stream("trigger")
        self._fire()

    def stream_fetch(self, timeout: float) -> tuple[Frame | None, int, int | None, str | None] | None:
        """The next frame of a stream, or None if none came within ``timeout`` s: (frame or None, frame
        id, camera timestamp in ns (exposure start), why the frame failed or None)."""
        buffer = self._pop(timeout)
        if buffer is None:
            return None
        frame, frame_id, stamp, failure = self._frame(buffer)
        return frame, frame_id, stamp or None, failure

    def stream_end(self) -> None:
        """Back to single grabs with the settings as they were."""
        if self._camera is None:
            self._stream_saved = None
            return
        saved, self._stream_saved = self._stream_saved or {}, None
        self._stop()
        self.trigger_source = saved.get("trigger_source", self.trigger_source)
        self._apply({**self._settings, "roi": self._settings.get("roi") or saved.get("roi")})
        self._arm(self.trigger_source)
        self._start()

    def statistics(self) -> dict[str, int]:
        """Aravis's stream counters: completed and failed buffers, underruns, resent and missing packets."""
        stream = self._require_stream("read statistics")
        aravis, _ = _aravis()
        completed, failures, underruns = aravis.Stream.get_statistics(stream)
        resent, missing = aravis.GvStream.get_statistics(stream)
        return {"completed": int(completed), "failures": int(failures), "underruns": int(underruns),
                "resent_packets": int(resent), "missing_packets": int(missing)}

    def _current_roi(self) -> Roi:
        camera = self._require_open("read the region of interest")
        _, glib = _aravis()
        try:
            x, y, width, height = camera.get_region()
        except glib.Error as error:
            raise self._lost_or(DeviceError, "read the region of interest", error.message) from None
        return Roi(int(x), int(y), int(width), int(height))

    # ------------------------------------------------------------------ helpers
    def _require_open(self, operation: str) -> Any:
        if self._camera is None:
            raise DeviceConnectionError(self._device, operation, "the camera is not open (call open() first)")
        if self._control_lost.is_set():
            raise DeviceConnectionError(self._device, operation, "control lost (the heartbeat failed)")
        return self._camera

    def _require_stream(self, operation: str) -> Any:
        self._require_open(operation)
        if self._stream is None:
            raise DeviceConnectionError(self._device, operation, "no stream (acquisition is not running)")
        return self._stream

    def _lost_or(self, kind: type[DeviceError], operation: str, message: str) -> DeviceError:
        if self._control_lost.is_set():
            return DeviceConnectionError(self._device, operation, "control lost (the heartbeat failed)")
        if "timeout" in message.lower():
            return DeviceTimeout(self._device, operation, message)
        return kind(self._device, operation, message)


_PFNC = {0x01080001: "Mono8", 0x01100005: "Mono12", 0x01100007: "Mono16", 0x01100003: "Mono10"}


def _format_name(code: int) -> str:
    return _PFNC.get(code, f"0x{code:08x}")
