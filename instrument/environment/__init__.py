"""Air and material: the refractive index of air (modified Edlén), the wavelength compensation of a
laser interferometer's displacement, and the correction of a length for the material's expansion.

Pure functions of SI values (K, Pa, relative humidity as a fraction, µmol/mol CO2, m); sources and
check values in ``docs/environment.md``.
"""

from instrument.environment._air import (
    CO2_RANGE_PPM,
    PRESSURE_RANGE_PA,
    TEMPERATURE_RANGE_K,
    WAVELENGTH_RANGE_M,
    ZERO_CELSIUS_K,
    refractive_index_of_air,
    saturation_vapour_pressure,
)
from instrument.environment._compensation import (
    HENE_VACUUM_WAVELENGTH_M,
    NOMINAL_AIR,
    REFERENCE_TEMPERATURE_K,
    AirConditions,
    WavelengthCompensation,
    material_expansion_correction,
    wavelength_compensation,
    wavelength_compensation_factor,
)
from instrument.environment._errors import AirConditionsError

__all__ = [
    "CO2_RANGE_PPM",
    "HENE_VACUUM_WAVELENGTH_M",
    "NOMINAL_AIR",
    "PRESSURE_RANGE_PA",
    "REFERENCE_TEMPERATURE_K",
    "TEMPERATURE_RANGE_K",
    "WAVELENGTH_RANGE_M",
    "ZERO_CELSIUS_K",
    "AirConditions",
    "AirConditionsError",
    "WavelengthCompensation",
    "material_expansion_correction",
    "refractive_index_of_air",
    "saturation_vapour_pressure",
    "wavelength_compensation",
    "wavelength_compensation_factor",
]
