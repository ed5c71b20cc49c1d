"""The environmental unit's readings: one ``EnvironmentReading`` per measuring cycle, assembled from
the cycle's air frame and material frame (matched on their cycle counter), and the checks that keep
a faulty or stale reading from being used.
"""

from __future__ import annotations

import math
import threading
import time

from drivers._errors import DeviceFault
from drivers.interferometer._interface import EnvironmentReading
from drivers.interferometer._layout import AIR_SENSORS, EnvironmentAirFrame, EnvironmentMaterialFrame

CYCLE_MODULUS = 16


class EnvironmentTracker:
    """The newest complete reading. Thread-safe: the receive thread feeds frames, readers ask."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._first = threading.Event()  # set by the first complete reading
        self._air: EnvironmentAirFrame | None = None
        self._reading: EnvironmentReading | None = None
        self._reading_mono = 0.0

    def on_air(self, frame: EnvironmentAirFrame) -> None:
        """The cycle's first frame: kept until its material frame arrives."""
        with self._lock:
            self._air = frame

    def on_material(self, frame: EnvironmentMaterialFrame, timestamp: float) -> tuple[bool, int]:
        """The cycle's second frame. Returns ``(complete, missed)``: whether it completed a reading
        (False when the air frame of its cycle never came, e.g. rejected for its CRC), and how many
        cycles were missed since the previous reading."""
        with self._lock:
            air, self._air = self._air, None
            if air is None or air.counter != frame.counter:
                return False, 0
            previous = self._reading
            self._reading = EnvironmentReading(
                timestamp=timestamp, received=time.time(), counter=frame.counter,
                air_temperature_k=air.air_temperature_k, pressure_pa=air.pressure_pa,
                relative_humidity=air.relative_humidity, material_temperatures_k=frame.temperatures_k,
                material_fitted=frame.fitted, faults=air.faults + frame.faults)
            self._reading_mono = time.monotonic()
        self._first.set()
        missed = 0 if previous is None else (frame.counter - previous.counter - 1) % CYCLE_MODULUS
        return True, missed

    def wait_first(self, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds for the first complete reading; whether there is one."""
        return self._first.wait(max(timeout, 0.0))

    def newest(self) -> tuple[EnvironmentReading | None, float]:
        """The newest reading and its age in seconds (host clock); ``(None, inf)`` before the first."""
        with self._lock:
            if self._reading is None:
                return None, math.inf
            return self._reading, time.monotonic() - self._reading_mono


def require_usable(device: str, operation: str, reading: EnvironmentReading) -> None:
    """Raise ``DeviceFault`` if a sensor reports a fault or an air sensor gives no reading."""
    if reading.faults:
        raise DeviceFault(device, operation, f"environmental sensor fault: {', '.join(reading.faults)}")
    missing = [name for name, value in zip(AIR_SENSORS, (reading.air_temperature_k, reading.pressure_pa,
                                                        reading.relative_humidity)) if math.isnan(value)]
    if missing:
        raise DeviceFault(device, operation, f"the environmental unit gives no {', '.join(missing)} reading")
