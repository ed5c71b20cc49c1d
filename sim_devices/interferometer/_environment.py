"""The head's environmental unit: air temperature, pressure and humidity sensors on the beam path,
up to three material sensors on the part, and what the air does to the head's reading.

The air is the cell's ``AmbientModel`` at ``world.clock() − origin``. Each sensor reads it with a
calibration offset (drawn once from the world's seed) and white noise, or reports a fault while the
operator's ``set_fault`` says so. The head's raw displacement is the geometric one times
n(air)/n(nominal), both indices from the twin's own Ciddor code (``_air.py``).
"""

from __future__ import annotations

import threading
from typing import Any

from sim_devices.ambient import AmbientConditions, AmbientModel
from sim_devices.interferometer import _air
from sim_devices.interferometer._config import InterferometerTwinConfig
from sim_devices.world import World

AIR_SENSORS = ("air_temperature", "pressure", "humidity")
MATERIAL_SENSORS = ("material1", "material2", "material3")
SENSORS = AIR_SENSORS + MATERIAL_SENSORS


class EnvironmentUnit:
    """Thread-safe model of the environmental unit on ``world`` (the seed, the clock)."""

    def __init__(self, world: World, config: InterferometerTwinConfig) -> None:
        self.world = world
        self.config = config
        self.ambient = AmbientModel(world.config.seed, config.ambient)
        self.origin = float(config.ambient_origin) if config.ambient_origin is not None else float(world.clock())
        self.fitted = AIR_SENSORS + MATERIAL_SENSORS[: config.ambient.material_sensors]
        errors = config.environment_sensors
        rng = world.rng("interferometer environment sensors")
        spread = {"air_temperature": errors.air_temperature_offset_std, "pressure": errors.pressure_offset_std,
                  "humidity": errors.humidity_offset_std}
        spread.update(dict.fromkeys(MATERIAL_SENSORS, errors.material_offset_std))
        self.offsets = {name: float(rng.normal(0.0, spread[name])) for name in SENSORS}
        self._noise = {"air_temperature": errors.air_temperature_noise, "pressure": errors.pressure_noise,
                       "humidity": errors.humidity_noise}
        self._noise.update(dict.fromkeys(MATERIAL_SENSORS, errors.material_noise))
        self._noise_rng = world.noise_rng("interferometer environment noise")
        self.nominal_index = _air.refractive_index(config.nominal_air_temperature_c, config.nominal_pressure_pa,
                                                   config.nominal_relative_humidity_percent, config.nominal_co2_ppm,
                                                   config.vacuum_wavelength)
        self._faulty: set[str] = set()
        self._lock = threading.Lock()

    # ------------------------------------------------------------------------------ the air
    def conditions(self, clock: float | None = None) -> AmbientConditions:
        """The true air at world-clock time ``clock`` (default: now)."""
        now = self.world.clock() if clock is None else clock
        return self.ambient.at(now - self.origin)

    def refractive_index(self, air: AmbientConditions) -> float:
        return _air.refractive_index(air.air_temperature_c, air.pressure_pa, air.relative_humidity_percent,
                                     air.co2_ppm, self.config.vacuum_wavelength)

    def refraction_ratio(self, air: AmbientConditions) -> float:
        """What the head's reading is scaled by in this air: n(air) / n(nominal), or 1."""
        return self.refractive_index(air) / self.nominal_index if self.config.air_refraction else 1.0

    # ------------------------------------------------------------------------------ the sensors
    def read(self, air: AmbientConditions) -> tuple[dict[str, float | None], set[str]]:
        """Every fitted sensor's reading of ``air`` (°C, Pa, % RH; offsets and noise included) and
        the set of sensors reporting a fault."""
        true = {"air_temperature": air.air_temperature_c, "pressure": air.pressure_pa,
                "humidity": air.relative_humidity_percent}
        true.update(zip(MATERIAL_SENSORS, air.material_temperatures_c))
        with self._lock:
            faulty = set(self._faulty)
            readings: dict[str, float | None] = {}
            for name in SENSORS:
                if name not in self.fitted:
                    readings[name] = None
                    continue
                noise = float(self._noise_rng.normal(0.0, self._noise[name])) if self._noise[name] else 0.0
                readings[name] = true[name] + self.offsets[name] + noise
        return readings, faulty

    def set_fault(self, sensor: str, faulty: bool = True) -> list[str]:
        """Make ``sensor`` report a fault (or stop); returns the sensors reporting one."""
        if sensor not in self.fitted:
            raise ValueError(f"interferometer twin: no sensor {sensor!r}; fitted: {', '.join(self.fitted)}")
        with self._lock:
            if faulty:
                self._faulty.add(sensor)
            else:
                self._faulty.discard(sensor)
            return sorted(self._faulty)

    def truth(self, clock: float | None = None) -> dict[str, Any]:
        """The true air now, the indices, the sensors' offsets and faults (JSON-friendly)."""
        now = self.world.clock() if clock is None else clock
        air = self.conditions(now)
        with self._lock:
            faulty = sorted(self._faulty)
        return {"clock": now, "origin": self.origin, "air": air.as_dict(),
                "refractive_index": self.refractive_index(air), "nominal_refractive_index": self.nominal_index,
                "refraction_ratio": self.refraction_ratio(air), "fitted": list(self.fitted),
                "sensor_offsets": {name: self.offsets[name] for name in self.fitted}, "faulty": faulty}
