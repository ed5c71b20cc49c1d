"""``PylonCamera``: Basler GigE/USB3 cameras (and the pylon camera emulator) through pypylon.

Settings (``PylonSettings``: a station file's camera entry with ``adapter: pylon``)
-----------------------------------------------------------------------------------
serial : str
    The camera's serial number (emulated cameras are ``0815-0000``, ``0815-0001`` …).
emulator_image : path, optional
    Serve this image file from an emulated camera: sets ``PYLON_CAMEMU=3`` (if not already set
    higher) before pypylon's first device enumeration, then ``TestImageSelector = Off``,
    ``ImageFileMode = On``, ``ImageFilename = <path>``. The emulator (pypylon 26.9) loads
    the file when acquisition starts, not at every grab; so before each trigger the adapter
    compares the file's (inode, mtime, size) with the one it loaded and restarts acquisition when
    the file was replaced (≈ 6 ms). A twin that replaces the file atomically therefore changes the
    next frame.
exposure_s, gain_db : float, optional
    ``ExposureTime`` (µs on the camera) or ``ExposureTimeAbs``; ``Gain`` in dB.
pixel_format : str, optional
    ``Mono8`` (default on the emulator), ``Mono10``, ``Mono12``, ``Mono16``.
roi : {offset_x, offset_y, width, height}, optional
software_trigger : bool, default True
    Each ``grab`` drains stale buffers, fires ``TriggerSoftware`` and waits for that exposure's
    frame: a frame is never older than the ``grab`` call. With ``False`` the camera free-runs and
    ``grab`` returns the next frame that arrives after the stale ones were drained.
trigger_source : str, optional
    ``"Software"`` (default with ``software_trigger``) or a hardware line (``"Line1"``): then
    ``grab`` only waits for the externally triggered frame.
retries : int, default 2
    Extra attempts after an incomplete buffer or a timeout, before the typed error is raised.
timeout_s : float, default 2.0
    Default grab timeout.

embedded_stamp : bool, default False
    The camera embeds a frame stamp in the image's first pixels (``drivers.camera._stamp``; the
    simulated cell's file cameras do): it becomes the frame's ``exposure_start``/``evidence`` and is
    blanked. Without it a real camera's software trigger bounds the exposure from below; an emulated
    camera's frames (a file's pixels) and hardware-triggered or free-running ones carry no evidence.

Errors: a camera that is not found or vanishes → ``DeviceConnectionError``; a frame that does not
come → ``DeviceTimeout``; an incomplete buffer → ``GrabFailed``. ``grab`` never returns None.
Host timestamps (``time.time()`` at retrieval): the emulator's ``TimeStamp`` is always 0.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from drivers._errors import DeviceConnectionError, DeviceError, DeviceTimeout
from drivers.camera._interface import Frame, GrabFailed, Roi
from drivers.camera._settings import PylonSettings
from drivers.camera._stamp import read_stamp, without_stamp

SATURATION = {"Mono8": 255, "Mono10": 1023, "Mono10p": 1023, "Mono12": 4095, "Mono12p": 4095,
              "Mono12Packed": 4095, "Mono16": 65535}
_EMULATED_CAMERAS = 3
_POLL_S = 0.001  # retrieve polling period


def _pylon():
    """Import pypylon lazily, so that importing ``drivers`` never needs the pylon runtime."""
    try:
        from pypylon import genicam, pylon
    except ImportError as error:  # pragma: no cover - pypylon is a declared dependency
        raise DeviceConnectionError("pylon", "import pypylon", f"pypylon is not installed ({error})") from None
    return pylon, genicam


def ensure_emulated_cameras(count: int = _EMULATED_CAMERAS) -> None:
    """Ask the pylon runtime for ``count`` emulated cameras (read at device enumeration)."""
    try:
        current = int(os.environ.get("PYLON_CAMEMU", "0"))
    except ValueError:
        current = 0
    if current < count:
        os.environ["PYLON_CAMEMU"] = str(count)


class PylonCamera:
    """One Basler camera selected by serial number; see the module docstring for the settings."""

    def __init__(self, settings: PylonSettings, *, name: str | None = None) -> None:
        self.settings = settings
        self.serial = settings.serial
        self.name = name or self.serial
        self.emulator_image = settings.emulator_image
        self.retries = settings.retries
        self.timeout_s = settings.timeout_s
        self._settings: dict[str, Any] = {
            "exposure_s": settings.exposure_s,
            "gain_db": settings.gain_db,
            "pixel_format": settings.pixel_format,
            "roi": settings.roi,
            "software_trigger": settings.software_trigger,
        }
        self.trigger_source = settings.trigger_source or ("Software" if settings.software_trigger else None)
        self._camera: Any = None
        self._frame_id = 0
        self.embedded_stamp = settings.embedded_stamp
        self._triggered_at: float | None = None  # host time of the last software trigger
        self._loaded_image: tuple[int, int, int] | None = None  # stat of the emulator file in use
        self._device = f"camera {self.name} ({self.serial})"
        self._stream_saved: dict[str, Any] | None = None  # what a stream changed, to put back

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        if self._camera is not None:
            return
        if self.emulator_image is not None:
            if not self.emulator_image.is_file():
                raise DeviceConnectionError(
                    self._device, "open", f"emulator image {self.emulator_image} does not exist"
                )
            ensure_emulated_cameras()
        pylon, genicam = _pylon()
        factory = pylon.TlFactory.GetInstance()
        try:
            devices = factory.EnumerateDevices()
        except genicam.GenericException as error:
            raise DeviceConnectionError(self._device, "enumerate cameras", str(error).split(" : ")[0]) from None
        matches = [d for d in devices if d.GetSerialNumber() == self.serial]
        if not matches:
            found = ", ".join(sorted(d.GetSerialNumber() for d in devices)) or "none"
            raise DeviceConnectionError(self._device, "open", f"no camera with serial {self.serial} (found: {found})")
        try:
            camera = pylon.InstantCamera(factory.CreateDevice(matches[0]))
            camera.Open()
        except genicam.GenericException as error:
            raise DeviceConnectionError(self._device, "open", str(error).split(" : ")[0]) from None
        self._camera = camera
        try:
            if self.emulator_image is not None:
                self._set("TestImageSelector", "Off")
                self._set("ImageFileMode", "On")
                self._set("ImageFilename", str(self.emulator_image.resolve()))
            self._apply(self._settings)
            self._start()
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        camera, self._camera = self._camera, None
        if camera is None:
            return
        _, genicam = _pylon()
        try:
            if camera.IsGrabbing():
                camera.StopGrabbing()
            camera.Close()
            camera.DestroyDevice()
        except genicam.GenericException:
            pass  # a vanished camera cannot be closed more than it already is

    def __enter__(self) -> PylonCamera:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def is_open(self) -> bool:
        return self._camera is not None

    # ------------------------------------------------------------------ settings
    def configure(self, *, exposure_s: float | None = None, gain_db: float | None = None,
                  pixel_format: str | None = None, roi: Roi | None = None,
                  software_trigger: bool | None = None) -> None:
        """Change settings; applied now when open (grabbing is paused around the change)."""
        changes = {
            k: v
            for k, v in {
                "exposure_s": exposure_s,
                "gain_db": gain_db,
                "pixel_format": pixel_format,
                "roi": roi,
                "software_trigger": software_trigger,
            }.items()
            if v is not None
        }
        self._settings.update(changes)
        if "software_trigger" in changes:
            self.trigger_source = "Software" if software_trigger else None
        if self._camera is None:
            return
        camera = self._camera
        was_grabbing = camera.IsGrabbing()
        if was_grabbing:
            camera.StopGrabbing()
        self._apply(changes)
        if was_grabbing or "software_trigger" in changes:
            self._start()

    def _apply(self, settings: Mapping[str, Any]) -> None:
        if settings.get("pixel_format") is not None:
            self._set("PixelFormat", settings["pixel_format"])
        if settings.get("roi") is not None:
            roi: Roi = settings["roi"]
            self._set("OffsetX", 0)
            self._set("OffsetY", 0)
            self._set("Width", roi.width)
            self._set("Height", roi.height)
            self._set("OffsetX", roi.offset_x)
            self._set("OffsetY", roi.offset_y)
        if settings.get("exposure_s") is not None:
            microseconds = float(settings["exposure_s"]) * 1e6
            self._set_first(("ExposureTime", "ExposureTimeAbs"), microseconds, "exposure")
        if settings.get("gain_db") is not None:
            self._set_first(("Gain", "GainAbs"), float(settings["gain_db"]), "gain in dB")
        self._set("TriggerSelector", "FrameStart", required=False)
        if self.trigger_source:
            self._set("TriggerMode", "On")
            self._set("TriggerSource", self.trigger_source)
        else:
            self._set("TriggerMode", "Off")

    def _start(self) -> None:
        pylon, genicam = _pylon()
        if self.emulator_image is not None:
            self._loaded_image = self._image_stamp()  # stat before the emulator reads the file
        try:
            self._camera.StartGrabbing(pylon.GrabStrategy_OneByOne)
        except genicam.GenericException as error:
            raise self._lost_or(DeviceError, "start grabbing", error) from None

    def _node(self, name: str):
        return self._camera.GetNodeMap().GetNode(name)

    def _set(self, name: str, value: Any, *, required: bool = True) -> None:
        _, genicam = _pylon()
        node = self._node(name)
        if node is None or not genicam.IsWritable(node):
            if required:
                raise DeviceError(self._device, f"set {name}", f"the camera has no writable {name}")
            return
        try:
            node.SetValue(value)
        except genicam.GenericException as error:
            raise DeviceError(self._device, f"set {name} = {value!r}", str(error).split(" : ")[0]) from None

    def _set_first(self, names: tuple[str, ...], value: Any, what: str) -> None:
        _, genicam = _pylon()
        for name in names:
            node = self._node(name)
            if node is not None and genicam.IsWritable(node):
                self._set(name, value)
                return
        raise DeviceError(self._device, f"set {what}", f"the camera has none of {', '.join(names)}")

    # ------------------------------------------------------------------ grabbing
    def trigger(self) -> None:
        """Drop stale frames, then fire the software trigger (nothing to do for hardware triggers)."""
        camera = self._require_open("trigger")
        pylon, genicam = _pylon()
        try:
            if self.emulator_image is not None and self._image_stamp() != self._loaded_image:
                camera.StopGrabbing()  # the emulator reads its image file only when acquisition starts
                self._start()
            for _ in range(64):  # drain frames exposed before this call
                stale = camera.RetrieveResult(0, pylon.TimeoutHandling_Return)
                if not stale.IsValid():
                    break
                stale.Release()
            if self.trigger_source == "Software":
                deadline = time.monotonic() + self.timeout_s  # polled, like retrieve()
                while not camera.WaitForFrameTriggerReady(0, pylon.TimeoutHandling_Return):
                    if time.monotonic() >= deadline:
                        raise DeviceTimeout(self._device, "trigger",
                                            f"not ready for a trigger within {self.timeout_s:.3g} s")
                    time.sleep(_POLL_S)
                self._triggered_at = time.time()  # the exposure cannot start before its trigger
                camera.ExecuteSoftwareTrigger()
        except genicam.GenericException as error:
            raise self._lost_or(GrabFailed, "trigger", error) from None

    def retrieve(self, timeout: float | None = None) -> Frame:
        """The next frame (one attempt, no retry)."""
        camera = self._require_open("retrieve frame")
        pylon, genicam = _pylon()
        timeout = self.timeout_s if timeout is None else float(timeout)
        # Poll instead of one timed RetrieveResult: under pytest-timeout's SIGALRM timer a timed
        # wait in the pylon runtime was seen to block past its timeout for good.
        deadline = time.monotonic() + timeout
        while True:
            try:
                result = camera.RetrieveResult(0, pylon.TimeoutHandling_Return)
            except genicam.GenericException as error:
                raise self._lost_or(GrabFailed, "retrieve frame", error) from None
            if result.IsValid() or time.monotonic() >= deadline:
                break
            time.sleep(_POLL_S)
        if not result.IsValid():
            if camera.IsCameraDeviceRemoved():
                raise DeviceConnectionError(self._device, "retrieve frame", "the camera was removed")
            raise DeviceTimeout(self._device, "retrieve frame", f"no frame within {timeout:.3g} s")
        try:
            if not result.GrabSucceeded():
                description = result.GetErrorDescription().strip() or "unknown error"
                raise GrabFailed(self._device, "retrieve frame", f"{description} (error 0x{result.GetErrorCode():x})")
            image = np.array(result.GetArray(), copy=True)
            pixel_format = camera.PixelFormat.GetValue()
        finally:
            result.Release()
        self._frame_id += 1
        exposure_start, evidence = self._evidence(image)
        return Frame(image, time.time(), self._frame_id, self.serial, SATURATION.get(pixel_format, int(image.max())),
                     exposure_start, evidence)

    def _evidence(self, image: np.ndarray) -> tuple[float | None, str | None]:
        """When the frame is known to show the scene (``Frame.exposure_start``, ``Frame.evidence``).

        An embedded stamp says it (and is blanked); an emulated camera's frame is the pixels of a file,
        so its trigger proves nothing about what they show; a real camera's software trigger bounds its
        exposure from below. A hardware-triggered or free-running camera without stamps gives none.
        """
        if self.embedded_stamp:
            stamp = read_stamp(image)
            if stamp is None:
                return None, None
            without_stamp(image)
            return stamp.time, "still since" if stamp.still else "exposure"
        if self.emulator_image is None and self.trigger_source == "Software" and self._triggered_at is not None:
            triggered, self._triggered_at = self._triggered_at, None
            return triggered, "exposure"
        return None, None

    def grab(self, timeout: float | None = None) -> Frame:
        """Trigger and retrieve one frame; incomplete buffers and timeouts are retried
        ``retries`` times before the typed error is raised. A vanished camera is not retried."""
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
    @property
    def emulated(self) -> bool:
        """Whether this is pylon's camera emulator serving files (``emulator_image``)."""
        return self.emulator_image is not None

    def stream_begin(self, *, exposure_s: float | None, roi: Roi | None, trigger_source: str,
                     sequence: Path | None = None) -> float:
        """Re-arm for a stream: ROI, exposure, ``FrameStart`` on ``trigger_source`` (rising edge), the
        chunks a real camera sends (``Timestamp``, frame counter), and for the emulator the frame
        sequence directory. Returns the camera's timestamp tick frequency (Hz). ``stream_end`` undoes it."""
        camera = self._require_open("start stream")
        _, genicam = _pylon()
        try:
            if camera.IsGrabbing():
                camera.StopGrabbing()
            if self._stream_saved is None:
                self._stream_saved = {k: self._node(k).GetValue() for k in ("Width", "Height", "OffsetX", "OffsetY")
                                      if self._node(k) is not None and genicam.IsReadable(self._node(k))}
            if roi is not None:
                self._apply({"roi": roi})
            if exposure_s is not None:
                self._set_first(("ExposureTime", "ExposureTimeAbs"), float(exposure_s) * 1e6, "exposure")
            self._set("TriggerSelector", "FrameStart", required=False)
            self._set("TriggerMode", "On")
            self._set("TriggerSource", trigger_source)
            self._set("TriggerActivation", "RisingEdge", required=False)
            frequency = 1e9
            if sequence is not None:
                self._set("ImageFilename", str(Path(sequence).resolve()))
            else:  # a real camera stamps and counts every frame in its chunk data
                self._set("ChunkModeActive", True, required=False)
                for selector in ("Timestamp", "Framecounter", "FrameID"):
                    node = self._node("ChunkSelector")
                    if node is not None and genicam.IsWritable(node) and selector in node.GetSymbolics():
                        node.SetValue(selector)
                        self._set("ChunkEnable", True, required=False)
                tick = self._node("GevTimestampTickFrequency")
                if tick is not None and genicam.IsReadable(tick):
                    frequency = float(tick.GetValue())
            pylon, _ = _pylon()
            camera.StartGrabbing(pylon.GrabStrategy_OneByOne)
        except genicam.GenericException as error:
            raise self._lost_or(DeviceError, "start stream", error) from None
        return frequency

    def stream_fire(self) -> None:
        """One software trigger (no draining, no restart: the stream's frames are all wanted)."""
        camera = self._require_open("trigger")
        pylon, genicam = _pylon()
        try:
            deadline = time.monotonic() + self.timeout_s
            while not camera.WaitForFrameTriggerReady(0, pylon.TimeoutHandling_Return):
                if time.monotonic() >= deadline:
                    raise DeviceTimeout(self._device, "trigger",
                                        f"not ready for a trigger within {self.timeout_s:.3g} s")
                time.sleep(_POLL_S)
            camera.ExecuteSoftwareTrigger()
        except genicam.GenericException as error:
            raise self._lost_or(GrabFailed, "trigger", error) from None

    def stream_fetch(self, timeout: float) -> tuple[Frame | None, int, int | None, str | None] | None:
        """The next grab result of a stream, or None if none came within ``timeout`` s: (frame or None,
        block id, chunk timestamp in ticks or None, why the buffer failed or None)."""
        camera = self._require_open("retrieve frame")
        pylon, genicam = _pylon()
        deadline = time.monotonic() + timeout
        while True:
            try:
                result = camera.RetrieveResult(0, pylon.TimeoutHandling_Return)
            except genicam.GenericException as error:
                raise self._lost_or(GrabFailed, "retrieve frame", error) from None
            if result.IsValid():
                break
            if time.monotonic() >= deadline:
                if camera.IsCameraDeviceRemoved():
                    raise DeviceConnectionError(self._device, "retrieve frame", "the camera was removed")
                return None
            time.sleep(_POLL_S / 2)
        try:
            block = int(result.GetBlockID())
            ticks: int | None = None
            for chunk in ("ChunkTimestamp",):
                with contextlib.suppress(Exception):
                    ticks = int(getattr(result, chunk).Value)
            if ticks is None or ticks == 0:
                ticks = int(result.GetTimeStamp()) or None  # the emulator's is always 0: no stamp
            if not result.GrabSucceeded():
                description = result.GetErrorDescription().strip() or "unknown error"
                return None, block, ticks, f"{description} (error 0x{result.GetErrorCode():x})"
            image = np.array(result.GetArray(), copy=True)
            pixel_format = camera.PixelFormat.GetValue()
        finally:
            result.Release()
        frame = Frame(image, time.time(), block, self.serial, SATURATION.get(pixel_format, int(image.max())))
        return frame, block, ticks, None

    def stream_end(self) -> None:
        """Back to single grabs: ROI, trigger source, chunks and the emulator's image as they were."""
        camera = self._camera
        if camera is None:
            self._stream_saved = None
            return
        _, genicam = _pylon()
        try:
            if camera.IsGrabbing():
                camera.StopGrabbing()
            self._set("ChunkModeActive", False, required=False)
            saved, self._stream_saved = self._stream_saved or {}, None
            for key in ("OffsetX", "OffsetY", "Width", "Height", "OffsetX", "OffsetY"):
                if key in saved:
                    self._set(key, saved[key], required=False)
            if self.emulator_image is not None:
                self._set("ImageFilename", str(self.emulator_image.resolve()))
            self._apply(self._settings)
            self._start()
        except genicam.GenericException as error:
            raise self._lost_or(DeviceError, "end stream", error) from None

    # ------------------------------------------------------------------ emulator helpers
    def _image_stamp(self) -> tuple[int, int, int] | None:
        if self.emulator_image is None:
            return None
        try:
            st = os.stat(self.emulator_image)
        except OSError:
            return None
        return (st.st_ino, st.st_mtime_ns, st.st_size)

    def force_failed_buffers(self, count: int) -> None:
        """Emulator only: make the next ``count`` frames incomplete (fault injection for tests)."""
        self._require_open("force failed buffers")
        self._set("ForceFailedBufferCount", int(count))
        self._node("ForceFailedBuffer").Execute()

    def _require_open(self, operation: str):
        if self._camera is None:
            raise DeviceConnectionError(self._device, operation, "the camera is not open (call open() first)")
        return self._camera

    def _lost_or(self, kind: type[DeviceError], operation: str, error: Exception) -> DeviceError:
        camera = self._camera
        try:
            removed = camera is not None and camera.IsCameraDeviceRemoved()
        except Exception:
            removed = True
        if removed:
            return DeviceConnectionError(self._device, operation, "the camera was removed")
        return kind(self._device, operation, str(error).split(" : ")[0])

