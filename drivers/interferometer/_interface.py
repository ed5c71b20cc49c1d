"""The laser interferometer interface every adapter implements. Displacements in metres."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from drivers._errors import DeviceError


class BeamInterrupted(DeviceError):
    """The beam was broken (or the signal too weak) inside the requested window."""


class DatumLost(BeamInterrupted):
    """No valid datum: never set since power-on, or the fringe count was lost when the beam broke
    (or the head was re-aimed). Displacements mean nothing until ``zero()`` sets a new datum."""


class FeedGap(DeviceError):
    """Samples were lost (a gap in the sample counter) or the feed went stale."""


@dataclass(frozen=True)
class Sample:
    timestamp: float  # seconds (device or host clock, as the adapter documents)
    displacement: float  # metres, relative to the current datum
    beam_ok: bool
    signal_strength: float  # 0..1
    counter: int


@runtime_checkable
class Interferometer(Protocol):
    name: str

    def open(self) -> None:
        """Connect (every wait bounded); raises ``DeviceConnectionError`` or ``DeviceTimeout``."""
        ...

    def close(self) -> None:
        """Release the connection (also after a failed or no ``open()``; calling it twice is harmless)."""
        ...

    def __enter__(self) -> Interferometer: ...

    def __exit__(self, *exc: object) -> None: ...

    def latest(self, max_age: float = 0.1) -> Sample:
        """The newest sample; raises ``FeedGap`` if it is older than ``max_age`` seconds."""
        ...

    def average(self, duration: float, timeout: float | None = None) -> float:
        """Mean displacement over the next ``duration`` seconds. Raises ``BeamInterrupted`` or
        ``FeedGap`` rather than averaging in bad or missing samples."""
        ...

    def zero(self) -> None:
        """Set the datum: the current position reads 0 from now on."""
        ...
