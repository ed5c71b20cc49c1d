"""The reference instruments' own uncertainty (Type B), and the wavelength compensation of a reading.

The station states no accuracy class for its references, so the numbers here are the usual
specifications of the instruments the cell is built from, written down once with where they come
from; the calibration record carries the values used (its provenance's ``references``), so an ISO
run's budget reads them from the record in force, never from here.

- Laser interferometer, environmental unit of the XC-80 class: air temperature ±0.2 K, pressure
  ±100 Pa, humidity ±6 % RH (half-widths, rectangular); the CO2 the unit cannot measure ±50 ppm
  about the assumed content; the modified Edlén equation's own 1e-8 (k = 2, so 0.5e-8 standard).
  Their effect on the wavelength compensation is computed from the equation at the recorded air
  (``scale_uncertainty``): about 0.2e-6 relative, i.e. 14 nm over 70 mm. An uncompensated head
  (``wavelength_compensation: false``) is off by the air's distance from nominal: taken as ±1 K,
  ±1000 Pa (about 1.6e-6 relative).
- The averaged reading's noise: 10 nm (resolution 1 nm, air turbulence over a short average);
  systematic at a calibration point, since it went into the curve there.
- Rotary table encoder: ±0.5″ (the accuracy class of a precision rotary table; the simulated
  table's reported error bound is below it), rectangular.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from instrument import ARCSEC
from instrument.environment import (
    HENE_VACUUM_WAVELENGTH_M,
    AirConditions,
    AirConditionsError,
    WavelengthCompensation,
    refractive_index_of_air,
    wavelength_compensation,
)

HENE_WAVELENGTH_M = HENE_VACUUM_WAVELENGTH_M
AIR_TEMPERATURE_HALF_WIDTH_K = 0.2
PRESSURE_HALF_WIDTH_PA = 100.0
HUMIDITY_HALF_WIDTH = 0.06
CO2_HALF_WIDTH_PPM = 50.0
EDLEN_STANDARD_UNCERTAINTY = 0.5e-8
UNCOMPENSATED_TEMPERATURE_HALF_WIDTH_K = 1.0
UNCOMPENSATED_PRESSURE_HALF_WIDTH_PA = 1000.0
INTERFEROMETER_READING_NOISE_M = 10e-9
TABLE_ENCODER_HALF_WIDTH_RAD = 0.5 * ARCSEC
TABLE_ENCODER_UNCERTAINTY_RAD = TABLE_ENCODER_HALF_WIDTH_RAD / math.sqrt(3.0)
NOMINAL_LAB_AIR = AirConditions(293.15, 101_325.0, 0.5, 400.0)


def scale_uncertainty(air: AirConditions | None, wavelength_m: float, *, compensated: bool = True) -> float:
    """Relative standard uncertainty of the interferometer's scale (its wavelength in air).

    Parameters
    ----------
    air : the air the readings were compensated for (their mean), or None (nominal laboratory air)
    wavelength_m : the laser's vacuum wavelength, m
    compensated : False for readings taken with the head's nominal air (no environmental unit)

    Returns
    -------
    float
        u(scale), relative: each sensor's rectangular half-width times the equation's sensitivity
        at ``air`` (by central differences), combined in quadrature with the equation's own.
    """
    base = air or NOMINAL_LAB_AIR
    if compensated:
        widths = {"temperature_k": AIR_TEMPERATURE_HALF_WIDTH_K, "pressure_pa": PRESSURE_HALF_WIDTH_PA,
                  "relative_humidity": HUMIDITY_HALF_WIDTH, "co2_ppm": CO2_HALF_WIDTH_PPM}
        floor = EDLEN_STANDARD_UNCERTAINTY
    else:
        widths = {"temperature_k": UNCOMPENSATED_TEMPERATURE_HALF_WIDTH_K,
                  "pressure_pa": UNCOMPENSATED_PRESSURE_HALF_WIDTH_PA}
        floor = 0.0
    values = base.as_record()
    total = floor**2
    for name, width in widths.items():
        step = width / 10.0
        high, low = dict(values), dict(values)
        high[name] += step
        low[name] -= step
        try:
            slope = (_index(high, wavelength_m) - _index(low, wavelength_m)) / (2.0 * step)
        except AirConditionsError:  # at the edge of the equation's range: one-sided would do, but this is Type B
            slope = 0.0
        total += (slope * width / math.sqrt(3.0)) ** 2
    return math.sqrt(total)


def _index(values: Mapping[str, float], wavelength_m: float) -> float:
    return float(refractive_index_of_air(values["temperature_k"], values["pressure_pa"],
                                         values["relative_humidity"], values["co2_ppm"], wavelength_m))


def compensate(raw_m: float, air: AirConditions, optics: Any) -> WavelengthCompensation:
    """The environment author's recipe: the head's nominal air from its ``optics`` (a ``HeadOptics``),
    the compensation of ``raw_m`` for ``air``."""
    nominal = AirConditions(optics.nominal_air_temperature, optics.nominal_pressure, optics.nominal_relative_humidity,
                            optics.nominal_co2)
    return wavelength_compensation(air, nominal, optics.vacuum_wavelength)


def interferometer_reference(scale: float, *, compensated: bool, air: Mapping[str, Any] | None,
                             frames_per_pose: int) -> dict[str, Any]:
    """The displacement reference as a calibration record's provenance states it (SI)."""
    return {"instrument": "laser interferometer", "components": ["x", "y", "z"], "frames_per_pose": frames_per_pose,
            "wavelength_compensation": "modified Edlén (instrument.environment)" if compensated else "none",
            "scale_standard_uncertainty": scale, "scale_distribution": "normal",
            "reading_noise_m": INTERFEROMETER_READING_NOISE_M, "mean_air": dict(air) if air else None,
            "basis": "XC-80-class environmental unit specification (procedures/kinds/_references.py)"}


def table_reference(frames_per_pose: int) -> dict[str, Any]:
    """The angle reference as a calibration record's provenance states it (SI)."""
    return {"instrument": "rotary table encoder", "components": ["a", "b", "c"], "frames_per_pose": frames_per_pose,
            "encoder_half_width_rad": TABLE_ENCODER_HALF_WIDTH_RAD,
            "encoder_standard_uncertainty_rad": TABLE_ENCODER_UNCERTAINTY_RAD, "encoder_distribution": "rectangular",
            "basis": "precision rotary table accuracy class ±0.5″ (procedures/kinds/_references.py)"}
