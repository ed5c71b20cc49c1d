"""``CameraTriplet``: the three screen cameras exposed together, one frame each."""

from __future__ import annotations

from collections.abc import Mapping

from drivers._errors import DeviceConnectionError, DeviceError, DeviceTimeout
from drivers.camera._interface import Camera, Frame, GrabFailed, Roi, TriggeredCamera
from drivers.camera._stream import FrameStream, StreamingCamera

DEFAULT_STREAM_EXPOSURE = 1e-3  # s, when neither the call nor the camera's settings give one


class CameraTriplet:
    """Triggers every camera, then collects one frame from each.

    Cameras with ``trigger()``/``retrieve()`` (``TriggeredCamera``) are all triggered first, so
    their exposures start within a few milliseconds of each other; others are grabbed in turn.
    When a camera fails, the whole set is re-triggered (so the frames stay from one instant), up
    to ``retries`` times; then the error names the camera(s) that did not deliver.

    Parameters
    ----------
    cameras : mapping name → Camera
        Usually ``{"x": ..., "y": ..., "z": ...}``.
    retries : int
        Extra attempts for the whole set after an incomplete buffer or a timeout.
    name : str
        Device name used in errors.
    """

    def __init__(self, cameras: Mapping[str, Camera], *, retries: int = 2, name: str = "cameras") -> None:
        if not cameras:
            raise ValueError("CameraTriplet needs at least one camera")
        self.cameras = dict(cameras)
        self.retries = int(retries)
        self.name = name

    def open(self) -> None:
        opened = []
        try:
            for camera in self.cameras.values():
                camera.open()
                opened.append(camera)
        except BaseException:
            for camera in opened:
                camera.close()
            raise

    def close(self) -> None:
        for camera in self.cameras.values():
            camera.close()

    def __enter__(self) -> CameraTriplet:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def grab(self, timeout: float = 2.0) -> dict[str, Frame]:
        """One frame per camera, keyed like ``cameras``; raises naming any camera that failed."""
        failures: dict[str, DeviceError] = {}
        for _attempt in range(self.retries + 1):
            frames, failures = self._attempt(timeout)
            lost = {k: e for k, e in failures.items() if isinstance(e, DeviceConnectionError)}
            if lost:
                raise DeviceConnectionError(self.name, "grab triplet", _describe(lost))
            if not failures:
                return frames
        kind = DeviceTimeout if all(isinstance(e, DeviceTimeout) for e in failures.values()) else GrabFailed
        raise kind(self.name, "grab triplet", f"{_describe(failures)} (after {self.retries + 1} attempts)")

    def _attempt(self, timeout: float) -> tuple[dict[str, Frame], dict[str, DeviceError]]:
        frames: dict[str, Frame] = {}
        failures: dict[str, DeviceError] = {}
        triggered: dict[str, TriggeredCamera] = {}
        for key, camera in self.cameras.items():
            if isinstance(camera, TriggeredCamera):
                try:
                    camera.trigger()
                    triggered[key] = camera
                except DeviceError as error:
                    failures[key] = error
        for key, camera in self.cameras.items():
            if key in failures:
                continue
            try:
                frames[key] = triggered[key].retrieve(timeout) if key in triggered else camera.grab(timeout)
            except DeviceError as error:
                failures[key] = error
        return frames, failures

    def start_stream(self, rate_hz: float, *, roi: Roi | Mapping[str, Roi | None] | None = None,
                     exposure_s: float | Mapping[str, float] | None = None, hardware_trigger: bool = True,
                     timeout: float = 30.0) -> FrameStream:
        """Trigger every camera together at ``rate_hz`` until ``stop()``; iterate the returned
        ``FrameStream`` for the frames, one ``StreamTriple`` per trigger (``drivers.camera._stream``).

        Parameters
        ----------
        rate_hz : float
            Pulses per second.
        roi : Roi or mapping camera → Roi, optional
            Region of interest per camera (a smaller one reads out faster: a camera misses pulses
            that come while it still reads out the previous frame).
        exposure_s : float or mapping camera → float, optional
            Default: each camera's ``exposure_s`` setting, else 1 ms.
        hardware_trigger : bool
            Real cameras: the common trigger line (``Line1``, or the camera's ``trigger_source``
            line) driven by the cell; False: software triggers from this process at ``rate_hz``.
            Emulated cameras: the simulated cell's trigger line either way.
        timeout : float
            Longest wait, s, for the next triple while iterating.

        Raises
        ------
        ValueError
            A rate out of (0, 10 kHz], a camera that cannot stream, or emulated and real cameras mixed.
        DeviceError, DeviceTimeout
            The cameras (or the simulated trigger line) could not be armed.
        """
        cameras: dict[str, StreamingCamera] = {}
        for key, camera in self.cameras.items():
            if not isinstance(camera, StreamingCamera):
                raise ValueError(f"{self.name}: camera {key} ({type(camera).__name__}) cannot stream")
            cameras[key] = camera
        rois = {key: (roi.get(key) if isinstance(roi, Mapping) else roi) for key in cameras}
        exposures = {}
        for key, camera in cameras.items():
            value = exposure_s.get(key) if isinstance(exposure_s, Mapping) else exposure_s
            value = value if value is not None else camera.settings.exposure_s
            exposures[key] = float(value if value is not None else DEFAULT_STREAM_EXPOSURE)
            if not 0 < exposures[key] < 1:
                raise ValueError(f"{self.name}: exposure of camera {key} must be in (0, 1) s, got {exposures[key]!r}")
        return FrameStream(cameras, rate_hz, exposures, rois, hardware_trigger, timeout, self.name)


def _describe(failures: Mapping[str, DeviceError]) -> str:
    return "; ".join(f"camera {key} missing: {error.cause}" for key, error in failures.items())
