"""The twin's physics of air: its refractive index by Ciddor's equation (Appl. Opt. 35, 1566 (1996)).

Written independently of the measurement core, which compensates with the modified Edlén equation:
the twin's air follows Ciddor (the International Association of Geodesy's reference, as NIST
computes it in its Engineering Metrology Toolbox, Appendix A-III), with water's saturation vapour
pressure by Davis (Metrologia 29, 67 (1992)) as in Ciddor's paper. In laboratory air the two
equations agree within about 1e-8, which is what a real interferometer's host lives with too.
"""

from __future__ import annotations

import math

_GAS_CONSTANT = 8.314472  # J/(mol K)
_WATER_MOLAR_MASS = 0.018015  # kg/mol
# Ciddor (1996): dispersion of standard dry air (15 °C, 101 325 Pa, 450 ppm CO2) and of water vapour
# (20 °C, 1333 Pa), both as refractivity; S = 1/λ² in µm⁻².
_K0, _K1, _K2, _K3 = 238.0185, 5_792_105.0, 57.362, 167_917.0
_W0, _W1, _W2, _W3 = 295.235, 2.6422, -0.03238, 0.004028
# Compressibility of moist air (BIPM, as in Ciddor's Appendix).
_A0, _A1, _A2 = 1.58123e-6, -2.9331e-8, 1.1043e-10
_B0, _B1, _C0, _C1 = 5.707e-6, -2.051e-8, 1.9898e-4, -2.376e-6
_D, _E = 1.83e-11, -0.765e-8
_STANDARD_PRESSURE, _STANDARD_TEMPERATURE, _STANDARD_COMPRESSIBILITY = 101_325.0, 288.15, 0.9995922115
_STANDARD_VAPOUR_DENSITY = 0.00985938  # kg/m³ of pure water vapour at 20 °C, 1333 Pa


def saturation_vapour_pressure(temperature_k: float) -> float:
    """Pa over liquid water (Davis 1992, as used by Ciddor)."""
    t = temperature_k
    return math.exp(1.2378847e-5 * t * t - 1.9121316e-2 * t + 33.93711047 - 6.3431645e3 / t)


def refractive_index(temperature_c: float, pressure_pa: float, relative_humidity_percent: float, co2_ppm: float,
                     wavelength_m: float) -> float:
    """Phase refractive index of moist air (Ciddor 1996) for the head's vacuum wavelength."""
    kelvin = temperature_c + 273.15
    s = (1e-6 / wavelength_m) ** 2
    dry_standard = 1e-8 * (_K1 / (_K0 - s) + _K3 / (_K2 - s)) * (1.0 + 0.534e-6 * (co2_ppm - 450.0))
    vapour_standard = 1.022e-8 * (_W0 + _W1 * s + _W2 * s * s + _W3 * s**3)
    dry_molar_mass = 0.0289635 + 1.2011e-8 * (co2_ppm - 400.0)

    enhancement = 1.00062 + 3.14e-8 * pressure_pa + 5.6e-7 * temperature_c**2
    vapour_fraction = enhancement * relative_humidity_percent / 100.0 * saturation_vapour_pressure(kelvin) / pressure_pa
    ratio = pressure_pa / kelvin
    compressibility = (1.0 - ratio * (_A0 + _A1 * temperature_c + _A2 * temperature_c**2
                                      + (_B0 + _B1 * temperature_c) * vapour_fraction
                                      + (_C0 + _C1 * temperature_c) * vapour_fraction**2)
                       + ratio**2 * (_D + _E * vapour_fraction**2))

    standard_dry_density = (_STANDARD_PRESSURE * dry_molar_mass
                            / (_STANDARD_COMPRESSIBILITY * _GAS_CONSTANT * _STANDARD_TEMPERATURE))
    molar_density = pressure_pa / (compressibility * _GAS_CONSTANT * kelvin)
    dry_density = (1.0 - vapour_fraction) * molar_density * dry_molar_mass
    vapour_density = vapour_fraction * molar_density * _WATER_MOLAR_MASS
    return (1.0 + dry_density / standard_dry_density * dry_standard
            + vapour_density / _STANDARD_VAPOUR_DENSITY * vapour_standard)
