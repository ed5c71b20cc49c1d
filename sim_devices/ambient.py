"""The ambient air of the simulated cell: a slow, seeded drift that is a pure function of time.

``AmbientModel(seed, config).at(t)`` gives the air temperature, pressure, relative humidity, CO2
content and the temperatures of up to three parts (material sensors) at ``t`` seconds of simulated
time. Nothing is stored between calls: every value is a sum of slow sinusoids (a daily cycle, an
air-conditioning cycle, the 12-hour atmospheric pressure tide) with seeded phases, and a bounded,
smooth random wander (value noise: seeded knot values hashed from the seed and the knot's index,
joined by a quintic smoothstep, two octaves). Any process that builds the model with the same seed
and configuration gets the same conditions at the same simulated time, without sharing state; the
processes only have to agree on the time origin (what ``t = 0`` is on the world clock).

The default drift is that of a temperature-controlled laboratory. Measured over a simulated week
for seeds 0-3 (one value a minute): the air within 19.57..20.43 °C, its change over an hour 0.10 K
in the median and at most 0.47 K; pressure within ±3 hPa of its mean, changing by 1.2 hPa a day in
the median and at most 4.8 hPa; humidity 41..49 % (−3 % per kelvin of warming plus its own
wander); CO2 420 ± 30 ppm. A part (a material sensor) follows the air's slow variation with a
first-order lag (``material_lag``, 15 min) at its own offset from the air. Set the means far from
20 °C / 101 325 Pa to put the cell in unusual air, and the amplitudes to 0 for constant air.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from sim_devices._config import checked_fields

MAX_MATERIAL_SENSORS = 3
_DAY = 86_400.0
_MASK64 = (1 << 64) - 1


@dataclass
class AmbientConfig:
    """Means, amplitudes (half the peak-to-peak swing) and time scales of the ambient drift."""

    air_temperature_c: float = 20.0  # mean air temperature, °C
    temperature_daily_amplitude: float = 0.2  # K, 24 h cycle
    temperature_cycle_amplitude: float = 0.02  # K, air-conditioning cycle
    temperature_cycle_period: float = 1200.0  # s
    temperature_wander: float = 0.25  # K, bound of the slow random wander
    temperature_wander_time: float = 3600.0  # s between its knots
    pressure_pa: float = 101_325.0  # mean total pressure, Pa
    pressure_wander: float = 300.0  # Pa: the weather
    pressure_wander_time: float = 86_400.0  # s
    pressure_tide_amplitude: float = 50.0  # Pa, 12 h atmospheric tide
    relative_humidity_percent: float = 45.0  # mean, %
    humidity_per_kelvin: float = -3.0  # % per K of air above its mean (same moisture, warmer air)
    humidity_wander: float = 3.0  # %
    humidity_wander_time: float = 7200.0  # s
    co2_ppm: float = 420.0  # mean, µmol/mol
    co2_wander: float = 30.0  # ppm (people in the room)
    co2_wander_time: float = 1800.0  # s
    material_sensors: int = 1  # parts with a temperature sensor, 0..3
    material_offsets: list[float] = field(default_factory=lambda: [0.2, -0.1, 0.05])  # K above the air, per part
    material_lag: float = 900.0  # s: time constant with which a part follows the air

    def __post_init__(self) -> None:
        for name in ("temperature_daily_amplitude", "temperature_cycle_amplitude", "temperature_wander",
                     "pressure_wander", "pressure_tide_amplitude", "humidity_wander", "co2_wander", "material_lag"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"ambient: {name} must be >= 0, got {getattr(self, name)!r}")
        for name in ("temperature_cycle_period", "temperature_wander_time", "pressure_wander_time",
                     "humidity_wander_time", "co2_wander_time"):
            if not getattr(self, name) > 0:
                raise ValueError(f"ambient: {name} must be > 0 s, got {getattr(self, name)!r}")
        if not -40.0 <= self.air_temperature_c <= 60.0:
            raise ValueError(f"ambient: air_temperature_c {self.air_temperature_c!r} is outside -40..60 °C")
        if not 50_000.0 <= self.pressure_pa <= 120_000.0:
            raise ValueError(f"ambient: pressure_pa {self.pressure_pa!r} is outside 50000..120000 Pa")
        if not 0.0 <= self.relative_humidity_percent <= 100.0:
            raise ValueError(f"ambient: relative_humidity_percent {self.relative_humidity_percent!r} is outside 0..100")
        if not 0.0 <= self.co2_ppm <= 2000.0:
            raise ValueError(f"ambient: co2_ppm {self.co2_ppm!r} is outside 0..2000")
        if not (isinstance(self.material_sensors, int) and 0 <= self.material_sensors <= MAX_MATERIAL_SENSORS):
            raise ValueError(f"ambient: material_sensors must be 0..{MAX_MATERIAL_SENSORS}, "
                             f"got {self.material_sensors!r}")
        if len(self.material_offsets) < self.material_sensors:
            raise ValueError(f"ambient: material_offsets needs one offset per material sensor "
                             f"({self.material_sensors}), got {list(self.material_offsets)!r}")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | AmbientConfig | None) -> AmbientConfig:
        if isinstance(data, AmbientConfig):
            return data
        return cls(**checked_fields(cls, data, "ambient config"))


@dataclass(frozen=True)
class AmbientConditions:
    """The true ambient at ``time`` (s of simulated time): °C, Pa, %, ppm, and one temperature (°C)
    per material sensor."""

    time: float
    air_temperature_c: float
    pressure_pa: float
    relative_humidity_percent: float
    co2_ppm: float
    material_temperatures_c: tuple[float, ...]

    def as_dict(self) -> dict[str, Any]:
        return {"time": self.time, "air_temperature_c": self.air_temperature_c, "pressure_pa": self.pressure_pa,
                "relative_humidity_percent": self.relative_humidity_percent, "co2_ppm": self.co2_ppm,
                "material_temperatures_c": list(self.material_temperatures_c)}


class AmbientModel:
    """The ambient drift for ``seed``: ``at(t)`` is a pure function of ``t`` (seconds).

    Parameters
    ----------
    seed : int
        The world's seed (the same seed gives the same air in every process).
    config : AmbientConfig or mapping, optional
        Means, amplitudes and time scales.
    """

    def __init__(self, seed: int, config: Mapping[str, Any] | AmbientConfig | None = None) -> None:
        self.seed = int(seed)
        self.config = AmbientConfig.from_dict(config)
        self._daily_phase = 2.0 * math.pi * self._unit("temperature daily phase", 0)
        self._cycle_phase = 2.0 * math.pi * self._unit("temperature cycle phase", 0)
        self._tide_phase = 2.0 * math.pi * self._unit("pressure tide phase", 0)

    def at(self, t: float) -> AmbientConditions:
        """The true conditions at ``t`` seconds of simulated time."""
        cfg = self.config
        t = float(t)
        swing = self._temperature_swing(t, lag=0.0)
        pressure = (cfg.pressure_pa + cfg.pressure_wander * self._wander("pressure", t, cfg.pressure_wander_time)
                    + cfg.pressure_tide_amplitude * math.sin(2.0 * math.pi * t / (_DAY / 2) + self._tide_phase))
        humidity = (cfg.relative_humidity_percent + cfg.humidity_per_kelvin * swing
                    + cfg.humidity_wander * self._wander("humidity", t, cfg.humidity_wander_time))
        co2 = cfg.co2_ppm + cfg.co2_wander * self._wander("co2", t, cfg.co2_wander_time)
        materials = tuple(cfg.air_temperature_c + cfg.material_offsets[i] + self._temperature_swing(t, cfg.material_lag)
                          for i in range(cfg.material_sensors))
        return AmbientConditions(time=t, air_temperature_c=cfg.air_temperature_c + swing, pressure_pa=pressure,
                                 relative_humidity_percent=min(100.0, max(0.0, humidity)),
                                 co2_ppm=max(0.0, co2), material_temperatures_c=materials)

    # ------------------------------------------------------------------------------ internals
    def _temperature_swing(self, t: float, lag: float) -> float:
        """The air temperature's departure from its mean, as a body with time constant ``lag`` sees it:
        each sinusoid through a first-order lag (attenuated and delayed exactly), the wander delayed by
        ``lag`` (its knots are an hour apart, so a 15 min lag barely attenuates it)."""
        cfg = self.config
        total = cfg.temperature_wander * self._wander("temperature", t - lag, cfg.temperature_wander_time)
        for amplitude, period, phase in ((cfg.temperature_daily_amplitude, _DAY, self._daily_phase),
                                         (cfg.temperature_cycle_amplitude, cfg.temperature_cycle_period,
                                          self._cycle_phase)):
            omega = 2.0 * math.pi / period
            total += amplitude / math.hypot(1.0, omega * lag) * math.sin(omega * t + phase - math.atan(omega * lag))
        return total

    def _wander(self, stream: str, t: float, knot_time: float) -> float:
        """Bounded smooth random wander in [-1, 1]: two octaves of value noise (0.9 at ``knot_time``,
        0.1 at a quarter of it)."""
        return 0.9 * self._value_noise(stream, t / knot_time) + 0.1 * self._value_noise(stream + " fine",
                                                                                        4.0 * t / knot_time)

    def _value_noise(self, stream: str, x: float) -> float:
        knot = math.floor(x)
        u = x - knot
        smooth = u * u * u * (u * (6.0 * u - 15.0) + 10.0)  # quintic: continuous slope and curvature
        first, second = (2.0 * self._unit(stream, k) - 1.0 for k in (knot, knot + 1))
        return first + (second - first) * smooth

    def _unit(self, stream: str, index: int) -> float:
        """A uniform number in [0, 1) hashed from (seed, stream, index): splitmix64 three times."""
        stream_state = _splitmix64(_splitmix64(self.seed & _MASK64) ^ zlib.crc32(stream.encode()))
        state = _splitmix64(stream_state ^ (index & _MASK64))
        return (state >> 11) * 2.0**-53


def _splitmix64(value: int) -> int:
    value = (value + 0x9E3779B97F4A7C15) & _MASK64
    value = ((value ^ (value >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    value = ((value ^ (value >> 27)) * 0x94D049BB133111EB) & _MASK64
    return value ^ (value >> 31)
