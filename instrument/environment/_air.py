"""The refractive index of air: the modified Edlén equation as NIST computes it.

Birch and Downs' updated Edlén equation (Metrologia 30, 155 (1993); correction Metrologia 31,
315 (1994)) with the temperature factor on the water-vapour term that Stone and Zimmerman add in
NIST's Engineering Metrology Toolbox ("Index of Refraction of Air", Appendix A-IV), and water's
saturation vapour pressure from IAPWS (Appendix A-I: over water at or above 0 °C, over ice below).
Its output reproduces NIST's modified-Edlén calculator to the last digit it prints (1e-9; the
check values are in ``tests/test_environment_core.py``). The equation's own uncertainty is about
1e-8 (k = 2) for 633 nm in ordinary laboratory air; an error of 1 K, 370 Pa or 100 % RH each moves
n by about 1e-6, so the sensors, not the equation, dominate.

Birch and Downs' standard air holds 450 µmol/mol of CO2; other contents are scaled as in Ciddor
(1996) and NIST's Appendix A-III, (n − 1) ∝ 1 + 0.534e-6 (x_CO2/ppm − 450) (±100 ppm moves n by
1.4e-8).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from instrument.environment._errors import AirConditionsError

ZERO_CELSIUS_K = 273.15

# Birch & Downs (1993/1994): dispersion of standard air, (n_s − 1)·1e8 = A + B/(130 − S) + C/(38.9 − S),
# S = 1/λ² in µm⁻²; density: (n_tp − 1) = p (n_s − 1) X / D, X = (1 + 1e-8 (E − F t) p) / (1 + G t).
_A, _B, _C = 8342.54, 2406147.0, 15998.0
_D, _E, _F, _G = 96095.43, 0.601, 0.00972, 0.003661
# Water vapour (NIST's temperature factor 292.75 / T on Birch & Downs' term): −1e-10 (292.75/T)(3.7345 − 0.0401 S) p_v.
_W0, _W1, _W_REFERENCE_K = 3.7345, 0.0401, 292.75
_CO2_REFERENCE_PPM, _CO2_PER_PPM = 450.0, 0.534e-6

# IAPWS-IF97 saturation line (NIST Appendix A-I), over water.
_K = (1.16705214528e03, -7.24213167032e05, -1.70738469401e01, 1.20208247025e04, -3.23255503223e06,
      1.49151086135e01, -4.82326573616e03, 4.05113405421e05, -2.38555575678e-01, 6.50175348448e02)
# IAPWS (2011) sublimation pressure, over ice.
_ICE_A1, _ICE_A2, _TRIPLE_POINT_K, _TRIPLE_POINT_PA = -13.928169, 34.7078238, 273.16, 611.657

# The ranges NIST's calculator accepts (its warnings start earlier: 350-1600 nm, 0-40 °C, 60-120 kPa).
WAVELENGTH_RANGE_M = (300e-9, 1700e-9)
TEMPERATURE_RANGE_K = (233.15, 373.15)
PRESSURE_RANGE_PA = (10e3, 140e3)
CO2_RANGE_PPM = (0.0, 2000.0)


def saturation_vapour_pressure(temperature_k: ArrayLike) -> NDArray[np.float64] | float:
    """Saturation vapour pressure of water in Pa: over liquid water at or above 273.15 K (IAPWS-IF97),
    over ice below (IAPWS 2011), as in NIST's Engineering Metrology Toolbox, Appendix A-I.

    Parameters
    ----------
    temperature_k : float or array_like
        Air temperature, K (233.15 to 373.15).

    Returns
    -------
    float or ndarray
        Pa; a float for a scalar input.
    """
    temperature = _checked("temperature_k", temperature_k, TEMPERATURE_RANGE_K, "K")
    omega = temperature + _K[8] / (temperature - _K[9])
    a = omega**2 + _K[0] * omega + _K[1]
    b = _K[2] * omega**2 + _K[3] * omega + _K[4]
    c = _K[5] * omega**2 + _K[6] * omega + _K[7]
    over_water = 1e6 * (2.0 * c / (-b + np.sqrt(b**2 - 4.0 * a * c))) ** 4
    theta = temperature / _TRIPLE_POINT_K
    over_ice = _TRIPLE_POINT_PA * np.exp(_ICE_A1 * (1.0 - theta**-1.5) + _ICE_A2 * (1.0 - theta**-1.25))
    return _scalar_or_array(np.where(temperature >= ZERO_CELSIUS_K, over_water, over_ice))


def refractive_index_of_air(
    temperature_k: ArrayLike, pressure_pa: ArrayLike, relative_humidity: ArrayLike, co2_ppm: ArrayLike = 400.0,
    wavelength_m: ArrayLike = 633e-9,
) -> NDArray[np.float64] | float:
    """Phase refractive index of moist air by the modified Edlén equation (Birch & Downs 1993/1994,
    with NIST's water-vapour term; see the module's docstring for the sources and check values).

    Parameters
    ----------
    temperature_k : float or array_like
        Air temperature, K (233.15 to 373.15).
    pressure_pa : float or array_like
        Total air pressure, Pa (10 kPa to 140 kPa).
    relative_humidity : float or array_like
        Relative humidity as a fraction (0 to 1), over water at or above 0 °C, over ice below.
    co2_ppm : float or array_like
        CO2 content, µmol/mol (0 to 2000). Default 400.
    wavelength_m : float or array_like
        Vacuum wavelength of the light, m (300 nm to 1700 nm). Default 633 nm (HeNe).

    Returns
    -------
    float or ndarray
        n (dimensionless, about 1.00027 in a laboratory); a float when every input is a scalar.

    Raises
    ------
    AirConditionsError
        An input that is not a finite number or is outside its range (one line naming it).
    """
    temperature = _checked("temperature_k", temperature_k, TEMPERATURE_RANGE_K, "K")
    pressure = _checked("pressure_pa", pressure_pa, PRESSURE_RANGE_PA, "Pa")
    humidity = _checked("relative_humidity", relative_humidity, (0.0, 1.0), "(a fraction)")
    co2 = _checked("co2_ppm", co2_ppm, CO2_RANGE_PPM, "ppm")
    wavelength = _checked("wavelength_m", wavelength_m, WAVELENGTH_RANGE_M, "m")

    celsius = temperature - ZERO_CELSIUS_K
    s = (1e-6 / wavelength) ** 2  # vacuum wavenumber squared, µm⁻²
    standard = 1e-8 * (_A + _B / (130.0 - s) + _C / (38.9 - s))
    standard = standard * (1.0 + _CO2_PER_PPM * (co2 - _CO2_REFERENCE_PPM))
    density = (1.0 + 1e-8 * (_E - _F * celsius) * pressure) / (1.0 + _G * celsius)
    dry = pressure * standard * density / _D
    vapour = humidity * saturation_vapour_pressure(temperature)
    water = 1e-10 * (_W_REFERENCE_K / temperature) * (_W0 - _W1 * s) * vapour
    return _scalar_or_array(1.0 + dry - water)


def _checked(name: str, value: ArrayLike, bounds: tuple[float, float], unit: str) -> NDArray[np.float64]:
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise AirConditionsError(f"{name} must be a number, got {value!r}") from None
    low, high = bounds
    bad = ~np.isfinite(array) | (array < low) | (array > high)
    if np.any(bad):
        first = float(array[bad].flat[0]) if array.ndim else float(array)
        raise AirConditionsError(f"{name} {first:g} is outside {low:g}..{high:g} {unit}")
    return array


def _scalar_or_array(array: NDArray[np.float64]) -> NDArray[np.float64] | float:
    return float(array) if array.ndim == 0 else array
