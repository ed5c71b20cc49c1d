"""``instrument.environment`` against published values: the refractive index of air (modified Edlén)
checked against NIST's calculators, water's saturation vapour pressure against IAPWS, and the
compensation and expansion formulas against their definitions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from instrument.environment import (
    NOMINAL_AIR,
    AirConditions,
    AirConditionsError,
    material_expansion_correction,
    refractive_index_of_air,
    saturation_vapour_pressure,
    wavelength_compensation,
    wavelength_compensation_factor,
)

CELSIUS = 273.15
# NIST Engineering Metrology Toolbox, "Wavelength calculator based on the modified Edlén equation"
# (emtoolbox.nist.gov/Wavelength/Edlen.asp), which prints n to 9 decimals; Edlén's standard air holds
# 450 ppm CO2. Values as recorded from that calculator in public code: 633, 350 and 400 nm at 20 °C,
# 101.325 kPa, 50 % RH (SpectralEvaluation's tests); 300..700 nm at 20 °C, 101.325 kPa, 30 % RH
# (a Geant4 material table, "based on Modified Edlen Equation, Engineering Metrology Toolbox").
NIST_EDLEN_50_PERCENT = {633.0: 1.000271374, 350.0: 1.000280826, 400.0: 1.000277516}
NIST_EDLEN_30_PERCENT = dict(zip(
    [300.0, 325.0, 350.0, 375.0, 400.0, 425.0, 450.0, 475.0, 500.0, 525.0, 550.0, 575.0, 600.0, 625.0, 650.0,
     675.0, 700.0],
    [1.000286349, 1.000283315, 1.000280985, 1.000279151, 1.000277679, 1.000276478, 1.000275484, 1.000274653,
     1.000273949, 1.000273348, 1.000272831, 1.000272382, 1.000271990, 1.000271646, 1.000271341, 1.000271071,
     1.000270830]))
HALF_LAST_DIGIT = 0.5e-9 + 1e-12

# NIST's Ciddor calculator (emtoolbox.nist.gov/Wavelength/Ciddor.asp), 450 ppm CO2, as recorded in the
# tests of the ref_index package: an independent equation, which the modified Edlén equation agrees
# with to within 1e-8 over 0..40 °C, 50..140 kPa, 0..100 % RH, 500..1000 nm (largest gap here 8.5e-9,
# at 0 °C).
NIST_CIDDOR = [  # (nm, °C, Pa, % RH, n)
    (633.0, 0.0, 101325.0, 50.0, 1.000291647), (633.0, 20.0, 101325.0, 50.0, 1.000271373),
    (633.0, 26.7982, 101325.0, 50.0, 1.000264994), (633.0, 40.123, 101325.0, 50.0, 1.000253031),
    (633.0, 20.0, 50123.0, 50.0, 1.000133999), (633.0, 20.0, 100123.4, 50.0, 1.000268148),
    (633.0, 20.0, 140000.0, 50.0, 1.000375169),
    (633.0, 20.0, 101325.0, 0.0, 1.0002718), (633.0, 20.0, 101325.0, 20.123, 1.000271627),
    (633.0, 20.0, 101325.0, 40.0, 1.000271458), (633.0, 20.0, 101325.0, 70.0, 1.000271203),
    (633.0, 20.0, 101325.0, 90.7432, 1.000271027), (633.0, 20.0, 101325.0, 100.0, 1.000270949),
    (500.0, 20.0, 101325.0, 50.0, 1.000273781), (600.1234, 20.0, 101325.0, 50.0, 1.000271818),
    (700.0, 20.0, 101325.0, 50.0, 1.000270657), (1000.987, 20.0, 101325.0, 50.0, 1.000269038),
]


@pytest.mark.parametrize(("nanometres", "expected"), sorted(NIST_EDLEN_50_PERCENT.items()))
def test_edlen_reproduces_nist_at_50_percent_humidity(nanometres, expected):
    n = refractive_index_of_air(293.15, 101325.0, 0.5, co2_ppm=450.0, wavelength_m=nanometres * 1e-9)
    assert abs(n - expected) <= HALF_LAST_DIGIT


def test_edlen_reproduces_nist_across_the_visible_at_30_percent_humidity():
    wavelengths = np.array(sorted(NIST_EDLEN_30_PERCENT)) * 1e-9
    n = refractive_index_of_air(293.15, 101325.0, 0.3, co2_ppm=450.0, wavelength_m=wavelengths)
    expected = np.array([NIST_EDLEN_30_PERCENT[key] for key in sorted(NIST_EDLEN_30_PERCENT)])
    assert isinstance(n, np.ndarray) and n.shape == expected.shape
    assert np.max(np.abs(n - expected)) <= HALF_LAST_DIGIT


@pytest.mark.parametrize(("nanometres", "celsius", "pascal", "percent", "expected"), NIST_CIDDOR)
def test_edlen_agrees_with_nists_ciddor_values(nanometres, celsius, pascal, percent, expected):
    n = refractive_index_of_air(celsius + CELSIUS, pascal, percent / 100.0, co2_ppm=450.0,
                                wavelength_m=nanometres * 1e-9)
    assert abs(n - expected) <= 1e-8


def test_sensitivities_near_nominal_air():
    def index(**change: float) -> float:
        air = {"temperature_k": 293.15, "pressure_pa": 101325.0, "relative_humidity": 0.5, **change}
        return float(refractive_index_of_air(air["temperature_k"], air["pressure_pa"], air["relative_humidity"]))

    per_kelvin = (index(temperature_k=293.65) - index(temperature_k=292.65)) / 1.0
    per_hectopascal = (index(pressure_pa=101375.0) - index(pressure_pa=101275.0)) / 1.0
    per_percent = (index(relative_humidity=0.55) - index(relative_humidity=0.45)) / 10.0
    # The rules of thumb of laser metrology: about -1 ppm/K, +0.27 ppm/hPa, -0.01 ppm/% RH.
    assert -0.97e-6 < per_kelvin < -0.94e-6
    assert 0.26e-6 < per_hectopascal < 0.28e-6
    assert -0.009e-6 < per_percent < -0.008e-6


def test_co2_scales_the_dry_refractivity():
    at_450 = refractive_index_of_air(293.15, 101325.0, 0.0, co2_ppm=450.0)
    at_350 = refractive_index_of_air(293.15, 101325.0, 0.0, co2_ppm=350.0)
    assert (at_350 - 1.0) / (at_450 - 1.0) == pytest.approx(1.0 - 0.534e-6 * 100.0, rel=1e-12)
    assert 1.3e-8 < at_450 - at_350 < 1.5e-8


def test_saturation_vapour_pressure_against_iapws():
    # IAPWS-IF97 (Table 35 of the release): p_s(300 K) = 3.53658941e-3 MPa.
    assert saturation_vapour_pressure(300.0) == pytest.approx(3536.58941, abs=1e-4)
    # At the triple point (611.657 Pa, from which IAPWS 2011 defines the ice branch) the water branch agrees.
    assert saturation_vapour_pressure(273.16) == pytest.approx(611.657, abs=0.01)
    # Below 0 °C the ice branch: 103.26 Pa at -20 °C, as the usual tables over ice give it.
    assert saturation_vapour_pressure(253.15) == pytest.approx(103.26, abs=0.05)
    assert saturation_vapour_pressure(293.15) == pytest.approx(2339.2, abs=0.1)


def test_nominal_air_needs_no_compensation():
    assert wavelength_compensation_factor(NOMINAL_AIR) == 1.0
    assert NOMINAL_AIR == AirConditions(293.15, 101325.0, 0.5, 400.0)


def test_compensation_factor_is_the_ratio_of_indices_and_is_recorded():
    warm_and_high = AirConditions(temperature_k=301.15, pressure_pa=92_000.0, relative_humidity=0.3, co2_ppm=420.0)
    compensation = wavelength_compensation(warm_and_high, wavelength_m=632.991e-9)
    n = refractive_index_of_air(301.15, 92_000.0, 0.3, 420.0, 632.991e-9)
    n_nominal = refractive_index_of_air(293.15, 101325.0, 0.5, 400.0, 632.991e-9)
    assert compensation.refractive_index == n and compensation.nominal_refractive_index == n_nominal
    assert compensation.factor == n_nominal / n
    assert wavelength_compensation_factor(warm_and_high, wavelength_m=632.991e-9) == compensation.factor
    # A head computing with n_nominal reads d·n/n_nominal; the compensation gives d back.
    true_displacement = 0.07
    raw = true_displacement * n / n_nominal
    assert compensation.apply(raw) == pytest.approx(true_displacement, abs=1e-15)
    assert 30e-6 < compensation.factor - 1.0 < 34e-6  # thin, warm air: the raw reading is 2.2 µm short at 70 mm
    record = compensation.as_record()
    assert record["conditions"] == {"temperature_k": 301.15, "pressure_pa": 92000.0, "relative_humidity": 0.3,
                                    "co2_ppm": 420.0}
    assert record["factor"] == compensation.factor and record["wavelength_m"] == 632.991e-9


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"temperature_k": 500.0}, "temperature_k 500 is outside 233.15..373.15 K"),
    ({"pressure_pa": 5000.0}, "pressure_pa 5000 is outside"),
    ({"relative_humidity": 45.0}, "relative_humidity 45 is outside 0..1"),
    ({"relative_humidity": math.nan}, "relative_humidity nan is outside"),
    ({"co2_ppm": -1.0}, "co2_ppm -1 is outside"),
    ({"wavelength_m": 633.0}, "wavelength_m 633 is outside"),
    ({"temperature_k": "warm"}, "temperature_k must be a number"),
])
def test_bad_conditions_are_one_clear_line(kwargs, message):
    arguments = {"temperature_k": 293.15, "pressure_pa": 101325.0, "relative_humidity": 0.5, **kwargs}
    with pytest.raises(AirConditionsError, match=message) as caught:
        refractive_index_of_air(**arguments)
    assert "\n" not in str(caught.value)


def test_material_expansion_correction_takes_a_length_to_20_degrees():
    steel = 11.5e-6
    measured = 0.1  # m, on a steel part at 25 °C
    correction = material_expansion_correction(measured, 298.15, steel)
    assert correction == pytest.approx(-measured * steel * 5.0 / (1.0 + steel * 5.0), rel=1e-12)
    assert correction == pytest.approx(-5.7497e-6, abs=1e-10)
    # The part at 20 °C has the length that, expanded by 5 K, is the measured one.
    assert (measured + correction) * (1.0 + steel * 5.0) == pytest.approx(measured, rel=1e-15)
    assert material_expansion_correction(measured, 293.15, steel) == 0.0
    assert material_expansion_correction(measured, 288.15, steel, reference_k=288.15) == 0.0
    assert material_expansion_correction(measured, 288.15, steel) > 0.0  # a cold part grows back


@pytest.mark.parametrize(("args", "message"), [
    ((0.1, 1000.0, 11.5e-6), "material_k 1000 K is outside"),
    ((0.1, 298.15, 0.5), "alpha_per_k 0.5 /K is not a linear expansion coefficient"),
    ((math.inf, 298.15, 11.5e-6), "length_m must be a finite number"),
    ((0.1, None, 11.5e-6), "material_k must be a finite number"),
])
def test_bad_expansion_input_is_one_clear_line(args, message):
    with pytest.raises(AirConditionsError, match=message):
        material_expansion_correction(*args)
