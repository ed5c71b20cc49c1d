"""Settings of the interferometer twin (the ``interferometer`` section of a cell config).

``FeedLayout`` is the head's reading of the documented frame layout settings
(``docs/interferometer.md``: ids, resolution, rates, under the same keys as a station file's
``layout``); the byte encoding itself is in ``_frames.py``. Neither comes from the driver.
``EnvironmentSensorConfig`` sets the errors of the environmental unit's sensors; the air they
measure is the cell's ``AmbientModel`` (``sim_devices.ambient``), configured by ``ambient``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from sim_devices._config import checked_fields
from sim_devices.ambient import AmbientConfig

_ID_KEYS = ("displacement_id", "status_id", "command_id", "reply_id", "environment_air_id", "environment_material_id")


@dataclass(frozen=True)
class FeedLayout:
    """CAN ids (standard 11-bit), resolution (m per count) and rates (Hz) of the feed the head sends."""

    displacement_id: int = 0x181
    status_id: int = 0x281
    command_id: int = 0x601
    reply_id: int = 0x581
    resolution: float = 1e-10
    sample_rate: float = 1000.0
    status_rate: float = 10.0
    environment_air_id: int = 0x381
    environment_material_id: int = 0x481
    environment_rate: float = 1.0

    def __post_init__(self) -> None:
        ids = [getattr(self, key) for key in _ID_KEYS]
        for key, can_id in zip(_ID_KEYS, ids):
            if not (isinstance(can_id, int) and 0 <= can_id <= 0x7FF):
                raise ValueError(f"interferometer twin layout: {key} {can_id!r} is not a standard 11-bit CAN id")
        if len(set(ids)) != len(ids):
            raise ValueError(f"interferometer twin layout: the CAN ids must differ, got {[hex(i) for i in ids]}")
        if not self.resolution > 0:
            raise ValueError(f"interferometer twin layout: resolution must be > 0 m, got {self.resolution!r}")
        if not 0 < self.sample_rate <= 10_000:
            raise ValueError(f"interferometer twin layout: sample_rate must be in (0, 10000] Hz, "
                             f"got {self.sample_rate!r}")
        if not 0 < self.status_rate <= self.sample_rate:
            raise ValueError(f"interferometer twin layout: status_rate must be in (0, sample_rate], "
                             f"got {self.status_rate!r}")
        if not 0 < self.environment_rate <= self.sample_rate:
            raise ValueError(f"interferometer twin layout: environment_rate must be in (0, sample_rate], "
                             f"got {self.environment_rate!r}")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | FeedLayout | None) -> FeedLayout:
        """From a ``layout`` mapping; ids may be ints or strings such as ``"0x181"``."""
        if isinstance(data, FeedLayout):
            return data
        settings = checked_fields(cls, data, "interferometer twin layout")
        for key in _ID_KEYS:
            if isinstance(settings.get(key), str):
                try:
                    settings[key] = int(settings[key], 0)
                except ValueError:
                    raise ValueError(f"interferometer twin layout: {key} {settings[key]!r} is not a number") from None
        return cls(**settings)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class EnvironmentSensorConfig:
    """Errors of the environmental unit's sensors: a calibration offset per sensor, drawn once from
    the world's seed (normal, with these standard deviations), plus white noise on every reading.
    The defaults are a calibrated unit of the XC-80 class (±0.2 K, ±1 hPa, ±6 % RH as limits)."""

    air_temperature_offset_std: float = 0.1  # K
    air_temperature_noise: float = 0.002  # K rms per reading
    pressure_offset_std: float = 50.0  # Pa
    pressure_noise: float = 1.0  # Pa
    humidity_offset_std: float = 2.0  # % RH
    humidity_noise: float = 0.1  # % RH
    material_offset_std: float = 0.1  # K, each material sensor
    material_noise: float = 0.002  # K

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if not value >= 0:
                raise ValueError(f"interferometer twin environment_sensors: {name} must be >= 0, got {value!r}")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | EnvironmentSensorConfig | None) -> EnvironmentSensorConfig:
        if isinstance(data, EnvironmentSensorConfig):
            return data
        return cls(**checked_fields(cls, data, "interferometer twin environment_sensors"))


@dataclass
class InterferometerTwinConfig:
    """Physics, transports and timing of the twin. Lengths in metres, angles in radians.

    The head's constants (scale error, misalignment at each ``align``, the environmental sensors'
    offsets) are drawn from the world's seeded random streams, so a seed reproduces them;
    ``scale_error`` pins the scale error instead.

    The head turns fringes into metres with the vacuum wavelength over the refractive index of the
    nominal air (``nominal_*``), so its reading is the geometric displacement times n(air)/n(nominal)
    (``air_refraction``; False: times 1, as if the beam ran in nominal air). The air is the
    ``ambient`` model at ``world.clock() − ambient_origin`` (None: the clock when the twin starts;
    give every twin of a cell the same origin and they all see the same air).
    """

    layout: FeedLayout = field(default_factory=FeedLayout)
    axis: str = "x"  # axis of M the head is aimed along at start
    # physics
    noise_std: float = 2e-9  # white displacement noise per sample
    scale_error: float | None = None  # None: drawn uniformly in ±scale_error_limit
    scale_error_limit: float = 0.5e-6
    misalignment_std: float = 5e-4  # per tilt component of the beam, redrawn at every align()
    lateral_range: float = 0.01  # signal = 0.95 exp(-(lateral offset / lateral_range)^2)
    beam_lost_signal: float = 0.10  # below this the head loses the fringe count
    low_signal: float = 0.30  # below this the "signal low" bit is set
    # air and the environmental unit
    ambient: AmbientConfig = field(default_factory=AmbientConfig)
    ambient_origin: float | None = None  # world-clock seconds at which the ambient model's time is 0
    environment_sensors: EnvironmentSensorConfig = field(default_factory=EnvironmentSensorConfig)
    air_refraction: bool = True
    vacuum_wavelength: float = 632.991e-9  # m, the head's stabilised HeNe
    nominal_air_temperature_c: float = 20.0
    nominal_pressure_pa: float = 101_325.0
    nominal_relative_humidity_percent: float = 50.0
    nominal_co2_ppm: float = 400.0
    # transports
    host: str = "127.0.0.1"
    port: int = 0
    channel: str = "can0"
    socketcand: bool = True
    slcan: bool = True
    first_frame_pause: float = 0.05  # s after the rawmode "< ok >" before the first frame
    can_bitrate: float = 1_000_000.0  # bit/s of the bus: a frame's time on it (its receive timestamp)
    rx_latency: float = 20e-6  # s, mean of the receiving kernel's timestamp latency tail
    # timing
    max_catch_up: float = 0.5  # s: a feed thread further behind than this drops (and counts) samples

    def __post_init__(self) -> None:
        if isinstance(self.layout, Mapping):
            self.layout = FeedLayout.from_dict(self.layout)
        if not isinstance(self.ambient, AmbientConfig):
            self.ambient = AmbientConfig.from_dict(self.ambient)
        if not isinstance(self.environment_sensors, EnvironmentSensorConfig):
            self.environment_sensors = EnvironmentSensorConfig.from_dict(self.environment_sensors)
        if not 300e-9 <= self.vacuum_wavelength <= 1700e-9:
            raise ValueError(f"interferometer twin: vacuum_wavelength must be 300..1700 nm, "
                             f"got {self.vacuum_wavelength!r}")
        if self.axis not in ("x", "y", "z"):
            raise ValueError(f"interferometer twin: axis must be 'x', 'y' or 'z', got {self.axis!r}")
        if not self.host.startswith("127."):
            raise ValueError(f"interferometer twin: host must be a loopback address, got {self.host!r}")
        if not (self.socketcand or self.slcan):
            raise ValueError("interferometer twin: enable at least one transport (socketcand, slcan)")
        for name in ("noise_std", "scale_error_limit", "misalignment_std", "first_frame_pause", "rx_latency"):
            if getattr(self, name) < 0:
                raise ValueError(f"interferometer twin: {name} must be >= 0, got {getattr(self, name)!r}")
        if not self.can_bitrate > 0:
            raise ValueError(f"interferometer twin: can_bitrate must be > 0 bit/s, got {self.can_bitrate!r}")
        if not self.lateral_range > 0:
            raise ValueError(f"interferometer twin: lateral_range must be > 0, got {self.lateral_range!r}")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | InterferometerTwinConfig | None) -> InterferometerTwinConfig:
        if isinstance(data, InterferometerTwinConfig):
            return data
        return cls(**checked_fields(cls, data, "interferometer twin config"))
