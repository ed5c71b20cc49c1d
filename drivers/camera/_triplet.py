"""``CameraTriplet``: the three screen cameras exposed together, one frame each."""

from __future__ import annotations

from collections.abc import Mapping

from drivers._errors import DeviceConnectionError, DeviceError, DeviceTimeout
from drivers.camera._interface import Camera, Frame, GrabFailed, TriggeredCamera


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

def _describe(failures: Mapping[str, DeviceError]) -> str:
    return "; ".join(f"camera {key} missing: {error.cause}" for key, error in failures.items())
