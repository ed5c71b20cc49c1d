"""The simulated cell's air: ``sim_devices.ambient.AmbientModel`` (a seeded drift that is a pure
function of time) and the interferometer twin's own refractive-index code (Ciddor) against NIST."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim_devices.ambient import AmbientConfig, AmbientModel
from sim_devices.interferometer import InterferometerTwinConfig
from sim_devices.interferometer._air import refractive_index as twin_refractive_index

WEEK_BY_MINUTES = np.arange(0.0, 7 * 86_400.0, 60.0)


def _series(model: AmbientModel, times=WEEK_BY_MINUTES) -> dict[str, np.ndarray]:
    conditions = [model.at(t) for t in times]
    return {"air": np.array([c.air_temperature_c for c in conditions]),
            "pressure": np.array([c.pressure_pa for c in conditions]),
            "humidity": np.array([c.relative_humidity_percent for c in conditions]),
            "co2": np.array([c.co2_ppm for c in conditions]),
            "material": np.array([c.material_temperatures_c for c in conditions])}


def test_the_same_seed_gives_the_same_air_without_shared_state():
    times = [0.0, 3600.5, -120.0, 1e6, 17.25]
    first, second = AmbientModel(7), AmbientModel(7)
    forwards = [first.at(t) for t in times]
    backwards = [second.at(t) for t in reversed(times)][::-1]  # order of calls does not matter
    assert forwards == backwards
    assert AmbientModel(8).at(3600.5) != first.at(3600.5)
    assert AmbientModel(7, {"pressure_pa": 95_000.0}).at(10.0).air_temperature_c == first.at(10.0).air_temperature_c


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_default_drift_is_a_temperature_controlled_laboratorys(seed):
    air = _series(AmbientModel(seed))
    # Bounds: mean ± (wander + daily + cycle amplitudes), pressure ± (wander + tide).
    assert np.all(np.abs(air["air"] - 20.0) <= 0.25 + 0.2 + 0.02)
    assert np.all(np.abs(air["pressure"] - 101_325.0) <= 300.0 + 50.0)
    assert np.all((air["humidity"] >= 45.0 - 3.0 - 3.0 * 0.47) & (air["humidity"] <= 45.0 + 3.0 + 3.0 * 0.47))
    assert np.all(np.abs(air["co2"] - 420.0) <= 30.0)
    # Slow: tenths of a kelvin per hour, hPa per day (measured: ≤ 0.47 K/h, ≤ 4.8 hPa/day for seeds 0..3).
    hourly = np.abs(air["air"][60:] - air["air"][:-60])
    daily = np.abs(air["pressure"][1440:] - air["pressure"][:-1440])
    assert 0.05 < float(np.median(hourly)) < 0.2 and float(np.max(hourly)) < 0.6
    assert 50.0 < float(np.median(daily)) < 250.0 and float(np.max(daily)) < 600.0
    # It really drifts (not a constant), and smoothly: a minute's step stays under the components'
    # steepest slopes added up (wander 0.014, its fine octave 0.006, air conditioning 0.006 K/min).
    assert float(np.ptp(air["air"])) > 0.4 and float(np.max(np.abs(np.diff(air["air"])))) < 0.0275


def test_humidity_falls_as_the_air_warms():
    config = {"humidity_wander": 0.0, "humidity_per_kelvin": -3.0}
    air = _series(AmbientModel(3, config))
    slope = np.polyfit(air["air"] - 20.0, air["humidity"] - 45.0, 1)[0]
    assert slope == pytest.approx(-3.0, abs=1e-9)


def test_a_part_follows_the_air_late_and_smoothed():
    config = {"material_sensors": 2, "material_offsets": [0.3, -0.2], "temperature_wander": 0.0,
              "temperature_daily_amplitude": 0.0, "temperature_cycle_amplitude": 0.1,
              "temperature_cycle_period": 3600.0, "material_lag": 900.0}
    day = np.arange(0.0, 86_400.0, 10.0)
    air = _series(AmbientModel(4, config), day)
    parts = air["material"]
    assert parts.shape == (day.size, 2)
    # Offsets from the air's mean, the swing attenuated by 1/sqrt(1 + (ωτ)²) and delayed by atan(ωτ)/ω.
    omega = 2 * math.pi / 3600.0
    gain = 1.0 / math.hypot(1.0, omega * 900.0)
    assert np.mean(parts, axis=0) == pytest.approx([20.3, 19.8], abs=1e-3)
    assert np.ptp(parts[:, 0]) / 2 == pytest.approx(0.1 * gain, rel=1e-3)
    lag = math.atan(omega * 900.0) / omega
    shift = round(lag / 10.0)
    delayed_air = np.roll(air["air"] - 20.0, shift)[shift:]
    assert np.max(np.abs(delayed_air * gain - (parts[shift:, 0] - 20.3))) < 0.1 * gain * 0.02


def test_constant_air_when_the_amplitudes_are_zero():
    still = {"temperature_daily_amplitude": 0.0, "temperature_cycle_amplitude": 0.0, "temperature_wander": 0.0,
             "pressure_wander": 0.0, "pressure_tide_amplitude": 0.0, "humidity_wander": 0.0, "co2_wander": 0.0,
             "air_temperature_c": 28.0, "pressure_pa": 92_000.0, "relative_humidity_percent": 30.0, "co2_ppm": 400.0}
    model = AmbientModel(5, still)
    for t in (0.0, 1234.5, 86_400.0 * 3):
        air = model.at(t)
        assert (air.air_temperature_c, air.pressure_pa, air.relative_humidity_percent, air.co2_ppm) == (
            28.0, 92_000.0, 30.0, 400.0)
        assert air.material_temperatures_c == (28.2,)


@pytest.mark.parametrize(("config", "message"), [
    ({"material_sensors": 4}, "material_sensors must be 0..3"),
    ({"material_sensors": 3, "material_offsets": [0.1]}, "one offset per material sensor"),
    ({"pressure_wander_time": 0.0}, "pressure_wander_time must be > 0 s"),
    ({"humidity_wander": -1.0}, "humidity_wander must be >= 0"),
    ({"pressure_pa": 20_000.0}, "pressure_pa 20000.0 is outside"),
    ({"temperature": 20.0}, "unknown field"),
])
def test_bad_ambient_settings_are_refused(config, message):
    with pytest.raises(ValueError, match=message):
        AmbientConfig.from_dict(config)


def test_the_twin_config_takes_the_ambient_and_the_sensor_errors():
    config = InterferometerTwinConfig.from_dict({"ambient": {"air_temperature_c": 25.0},
                                                 "environment_sensors": {"pressure_offset_std": 0.0}})
    assert config.ambient.air_temperature_c == 25.0 and config.environment_sensors.pressure_offset_std == 0.0
    with pytest.raises(ValueError, match="unknown field"):
        InterferometerTwinConfig.from_dict({"environment_sensors": {"pressure_std": 1.0}})
    with pytest.raises(ValueError, match="environment_rate"):
        InterferometerTwinConfig.from_dict({"layout": {"environment_rate": 0.0}})


# NIST's Ciddor calculator (emtoolbox.nist.gov/Wavelength/Ciddor.asp), 450 ppm CO2, as recorded in the
# tests of the ref_index package; it prints n to 9 decimals.
NIST_CIDDOR = [  # (nm, °C, Pa, % RH, n)
    (633.0, 0.0, 101325.0, 50.0, 1.000291647), (633.0, 20.0, 101325.0, 50.0, 1.000271373),
    (633.0, 40.123, 101325.0, 50.0, 1.000253031), (633.0, 20.0, 50123.0, 50.0, 1.000133999),
    (633.0, 20.0, 140000.0, 50.0, 1.000375169), (633.0, 20.0, 101325.0, 0.0, 1.0002718),
    (633.0, 20.0, 101325.0, 100.0, 1.000270949), (500.0, 20.0, 101325.0, 50.0, 1.000273781),
    (1000.987, 20.0, 101325.0, 50.0, 1.000269038),
]


@pytest.mark.parametrize(("nanometres", "celsius", "pascal", "percent", "expected"), NIST_CIDDOR)
def test_the_twins_air_is_ciddors(nanometres, celsius, pascal, percent, expected):
    # Within NIST's rounding plus the gap between Davis's and IAPWS's vapour pressure (< 1e-10 here).
    n = twin_refractive_index(celsius, pascal, percent, 450.0, nanometres * 1e-9)
    assert abs(n - expected) <= 0.6e-9
