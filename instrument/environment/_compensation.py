"""Wavelength compensation of a laser interferometer's displacement, and the material's expansion.

A fringe-counting head turns N fringes into a length with the wavelength in air, λ_vac / n. A head
that uses a fixed nominal index n_nominal (that of ``NOMINAL_AIR``) reports

    d_raw = d_true · n / n_nominal

when the air's real index is n, so the geometric displacement is

    d_true = d_raw · n_nominal / n = d_raw · factor.

Near nominal air n changes by −0.955 ppm per kelvin, +0.268 ppm per hPa and −0.0085 ppm per % RH,
so the factor by as much the other way (over 70 mm of travel: 67 nm per K, 19 nm per hPa).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from instrument.environment._air import ZERO_CELSIUS_K, refractive_index_of_air
from instrument.environment._errors import AirConditionsError

HENE_VACUUM_WAVELENGTH_M = 632.991e-9  # a stabilised HeNe laser's vacuum wavelength, m
REFERENCE_TEMPERATURE_K = 293.15  # ISO 1: the reference temperature of dimensional measurement, 20 °C


@dataclass(frozen=True)
class AirConditions:
    """Air along the beam: temperature (K), total pressure (Pa), relative humidity (a fraction
    0..1) and CO2 content (µmol/mol)."""

    temperature_k: float
    pressure_pa: float
    relative_humidity: float
    co2_ppm: float = 400.0

    def as_record(self) -> dict[str, float]:
        """The four values by name (SI; JSON-friendly)."""
        return {key: float(value) for key, value in asdict(self).items()}


NOMINAL_AIR = AirConditions(temperature_k=ZERO_CELSIUS_K + 20.0, pressure_pa=101_325.0, relative_humidity=0.5,
                            co2_ppm=400.0)
"""The air a head without compensation assumes: 20 °C, 101 325 Pa, 50 % RH, 400 ppm CO2."""


@dataclass(frozen=True)
class WavelengthCompensation:
    """The compensation of one displacement reading, with everything needed to record it.

    ``factor`` multiplies a displacement computed with ``nominal`` air's index to give the
    geometric displacement in the air of ``conditions``.
    """

    conditions: AirConditions
    nominal: AirConditions
    wavelength_m: float
    refractive_index: float
    nominal_refractive_index: float

    @property
    def factor(self) -> float:
        """n_nominal / n (dimensionless, within a few 1e-5 of 1 in any laboratory)."""
        return self.nominal_refractive_index / self.refractive_index

    def apply(self, raw_displacement_m: float) -> float:
        """The geometric displacement (m) for a displacement ``raw_displacement_m`` (m) the head
        computed with the nominal index."""
        return float(raw_displacement_m) * self.factor

    def as_record(self) -> dict[str, object]:
        """Conditions, nominal, wavelength, both indices and the factor (SI; JSON-friendly)."""
        return {"conditions": self.conditions.as_record(), "nominal": self.nominal.as_record(),
                "wavelength_m": self.wavelength_m, "refractive_index": self.refractive_index,
                "nominal_refractive_index": self.nominal_refractive_index, "factor": self.factor,
                "equation": "modified Edlén (Birch & Downs 1993/1994, NIST water-vapour term)"}


def wavelength_compensation(conditions: AirConditions, nominal: AirConditions = NOMINAL_AIR,
                            wavelength_m: float = HENE_VACUUM_WAVELENGTH_M) -> WavelengthCompensation:
    """The wavelength compensation for air ``conditions`` of a head that assumes ``nominal`` air.

    Parameters
    ----------
    conditions : AirConditions
        The air measured along the beam (the environmental unit's reading).
    nominal : AirConditions
        The air whose refractive index the head uses to turn fringes into metres.
    wavelength_m : float
        The laser's vacuum wavelength, m.

    Returns
    -------
    WavelengthCompensation
        Both refractive indices and the factor n_nominal / n.

    Raises
    ------
    AirConditionsError
        Conditions outside the equation's range (one line naming the value).
    """
    actual = refractive_index_of_air(conditions.temperature_k, conditions.pressure_pa,
                                     conditions.relative_humidity, conditions.co2_ppm, wavelength_m)
    assumed = refractive_index_of_air(nominal.temperature_k, nominal.pressure_pa, nominal.relative_humidity,
                                      nominal.co2_ppm, wavelength_m)
    return WavelengthCompensation(conditions, nominal, float(wavelength_m), float(actual), float(assumed))


def wavelength_compensation_factor(conditions: AirConditions, nominal: AirConditions = NOMINAL_AIR,
                                   wavelength_m: float = HENE_VACUUM_WAVELENGTH_M) -> float:
    """n_nominal / n: multiply a displacement computed with ``nominal`` air's index by it.

    Parameters
    ----------
    conditions : AirConditions
        The air measured along the beam.
    nominal : AirConditions
        The air the head assumes.
    wavelength_m : float
        The laser's vacuum wavelength, m.

    Returns
    -------
    float
        The factor: about 1 + 0.955e-6 per K of air above nominal, − 0.268e-6 per hPa above,
        + 0.0085e-6 per % RH above.
    """
    return wavelength_compensation(conditions, nominal, wavelength_m).factor


def material_expansion_correction(length_m: float, material_k: float, alpha_per_k: float,
                                  reference_k: float = REFERENCE_TEMPERATURE_K) -> float:
    """The correction (m) that takes a length measured on a part at ``material_k`` to the length
    the part has at ``reference_k`` (linear expansion): ``length_at_reference = length_m + correction``.

    L_ref = L / (1 + α (T − T_ref)), so the correction is −L α (T − T_ref) / (1 + α (T − T_ref)).
    This is what a laser system's "material compensation" applies to normalise a machine axis or a
    part to 20 °C; a robot's pose is measured where it is, so the displacement calibration records
    the material temperature rather than applying this.

    Parameters
    ----------
    length_m : float
        The length measured at ``material_k``, m.
    material_k : float
        The part's temperature, K.
    alpha_per_k : float
        The part's linear expansion coefficient, 1/K (steel ≈ 11.5e-6, aluminium ≈ 23e-6).
    reference_k : float
        The temperature the length is referred to, K (default 293.15, ISO 1).

    Returns
    -------
    float
        m (negative when the part is warmer than the reference and α > 0).

    Raises
    ------
    AirConditionsError
        A value that is not a finite number, a temperature outside 173.15..473.15 K, or
        |α| ≥ 1e-3 /K (one line naming it).
    """
    for name, value in (("length_m", length_m), ("material_k", material_k), ("alpha_per_k", alpha_per_k),
                        ("reference_k", reference_k)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise AirConditionsError(f"{name} must be a finite number, got {value!r}")
    for name, value in (("material_k", material_k), ("reference_k", reference_k)):
        if not 173.15 <= value <= 473.15:
            raise AirConditionsError(f"{name} {value:g} K is outside 173.15..473.15 K")
    if abs(alpha_per_k) >= 1e-3:
        raise AirConditionsError(f"alpha_per_k {alpha_per_k:g} /K is not a linear expansion coefficient "
                                 "(|alpha| < 1e-3 /K)")
    strain = alpha_per_k * (material_k - reference_k)
    return -length_m * strain / (1.0 + strain)
