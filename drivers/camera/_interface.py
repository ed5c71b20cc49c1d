"""The camera interface every adapter implements."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from drivers._errors import DeviceError


class GrabFailed(DeviceError):
    """A frame could not be grabbed (incomplete buffer, timeout after retries, camera vanished)."""


@dataclass(frozen=True)
class Frame:
    """One grabbed image.

    Attributes
    ----------
    image : 2-D uint8 or uint16 array, ``image[row, col]``.
    timestamp : float
        Host time (``time.time()``, seconds) when the frame was retrieved.
    frame_id : int
        The camera's (or the adapter's) running frame number.
    camera : str
        Serial number or name of the camera.
    saturation : int
        The pixel value that means "saturated" for this pixel format (255, 4095, ...).
    exposure_start : float or None
        Host wall-clock time (``time.time()`` scale, s) the frame is known to show the scene at or
        after, or None when the camera gives no such evidence. What it means is ``evidence``.
    evidence : str or None
        ``"exposure"``: the exposure started at ``exposure_start`` (a camera clock mapped to the host,
        or a trigger sent then); ``"still since"``: the frame shows a scene that has been still since
        ``exposure_start`` (an embedded stamp of the simulated file cameras).
    """

    image: np.ndarray
    timestamp: float
    frame_id: int
    camera: str
    saturation: int
    exposure_start: float | None = None
    evidence: str | None = None


@dataclass(frozen=True)
class Roi:
    offset_x: int
    offset_y: int
    width: int
    height: int


@runtime_checkable
class Camera(Protocol):
    """One camera. ``grab`` always returns a frame or raises; it never returns None."""

    name: str

    def open(self) -> None:
        """Connect (every wait bounded); raises ``DeviceConnectionError`` or ``DeviceTimeout``."""
        ...

    def close(self) -> None:
        """Release the connection (also after a failed or no ``open()``; calling it twice is harmless)."""
        ...

    def __enter__(self) -> Camera: ...

    def __exit__(self, *exc: object) -> None: ...

    def configure(
        self,
        *,
        exposure_s: float | None = None,
        gain_db: float | None = None,
        pixel_format: str | None = None,
        roi: Roi | None = None,
        software_trigger: bool | None = None,
    ) -> None: ...

    def grab(self, timeout: float = 2.0) -> Frame: ...


@runtime_checkable
class TriggeredCamera(Camera, Protocol):
    """A camera that can be triggered and read in two steps, so that several cameras expose
    together (``CameraTriplet``): ``trigger()`` starts an exposure now, ``retrieve(timeout)``
    returns that exposure's frame (one attempt, no retry) or raises."""

    def trigger(self) -> None: ...

    def retrieve(self, timeout: float = 2.0) -> Frame: ...
