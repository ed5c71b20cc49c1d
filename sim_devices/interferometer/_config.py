"""Settings of the interferometer twin (the ``interferometer`` section of a cell config)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from drivers._config import checked_fields
from drivers.interferometer._layout import FrameLayout


@dataclass
class InterferometerTwinConfig:
    """Physics, transports and timing of the twin. Lengths in metres, angles in radians.

    The head's constants (scale error, misalignment at each ``align``) are drawn from the world's
    seeded random streams, so a seed reproduces them; ``scale_error`` pins the scale error instead.
    """

    layout: FrameLayout = field(default_factory=FrameLayout)
    axis: str = "x"  # axis of M the head is aimed along at start
    # physics
    noise_std: float = 2e-9  # white displacement noise per sample
    scale_error: float | None = None  # None: drawn uniformly in ±scale_error_limit
    scale_error_limit: float = 0.5e-6
    misalignment_std: float = 5e-4  # per tilt component of the beam, redrawn at every align()
    lateral_range: float = 0.01  # signal = 0.95 exp(-(lateral offset / lateral_range)^2)
    beam_lost_signal: float = 0.10  # below this the head loses the fringe count
    low_signal: float = 0.30  # below this the "signal low" bit is set
    # transports
    host: str = "127.0.0.1"
    port: int = 0
    channel: str = "can0"
    socketcand: bool = True
    slcan: bool = True
    first_frame_pause: float = 0.05  # s after the rawmode "< ok >" before the first frame
    # timing
    max_catch_up: float = 0.5  # s: a feed thread further behind than this drops (and counts) samples

    def __post_init__(self) -> None:
        if isinstance(self.layout, Mapping):
            self.layout = FrameLayout.from_dict(self.layout)
        if self.axis not in ("x", "y", "z"):
            raise ValueError(f"interferometer twin: axis must be 'x', 'y' or 'z', got {self.axis!r}")
        if not self.host.startswith("127."):
            raise ValueError(f"interferometer twin: host must be a loopback address, got {self.host!r}")
        if not (self.socketcand or self.slcan):
            raise ValueError("interferometer twin: enable at least one transport (socketcand, slcan)")
        for name in ("noise_std", "scale_error_limit", "misalignment_std", "first_frame_pause"):
            if getattr(self, name) < 0:
                raise ValueError(f"interferometer twin: {name} must be >= 0, got {getattr(self, name)!r}")
        if not self.lateral_range > 0:
            raise ValueError(f"interferometer twin: lateral_range must be > 0, got {self.lateral_range!r}")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | InterferometerTwinConfig | None) -> InterferometerTwinConfig:
        if isinstance(data, cls):
            return data
        return cls(**checked_fields(cls, data, "interferometer twin config"))
