"""The laser interferometer interface every adapter implements. Displacements in metres; the
environmental unit's readings in kelvin, pascal and relative humidity as a fraction."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

from drivers._errors import DeviceError

if TYPE_CHECKING:
    from drivers.interferometer._settings import HeadOptics


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


@dataclass(frozen=True)
class EnvironmentReading:
    """One measuring cycle of the head's environmental unit (air along the beam, material sensors).

    ``timestamp`` is the material frame's timestamp as the adapter documents it for samples (the
    cycle's receive time on the bus for socketcand, the host's clock for slcan); ``received`` the
    host's clock (``time.time()``) when the driver assembled the reading. A value is NaN when there
    is no reading: a sensor not fitted (``material_fitted`` False) or reporting a fault (its name
    in ``faults``: ``air_temperature``, ``pressure``, ``humidity``, ``material1``..``material3``).
    """

    timestamp: float
    received: float
    counter: int  # cycle counter, mod 16
    air_temperature_k: float
    pressure_pa: float
    relative_humidity: float  # a fraction, 0..1
    material_temperatures_k: tuple[float, float, float]
    material_fitted: tuple[bool, bool, bool]
    faults: tuple[str, ...]


@runtime_checkable
class Interferometer(Protocol):
    name: str
    optics: HeadOptics  # the vacuum wavelength and the nominal air the head computes displacements with

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

    def environment(self, max_age: float | None = None, *, strict: bool = True) -> EnvironmentReading:
        """The newest reading of the environmental unit; ``FeedGap`` if it is older than ``max_age``
        seconds (default: three measuring cycles) or, right after ``open``, if none has come within
        1.5 measuring cycles; ``DeviceFault`` if a sensor reports a fault or an air sensor gives no
        reading (unless ``strict`` is False: then the reading, NaN where none)."""
        ...
