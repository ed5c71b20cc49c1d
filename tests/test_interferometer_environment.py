"""The environmental unit end to end: the driver's ``environment()`` against the twin's air over both
transports, its typed errors, and the wavelength compensation of ``instrument.environment`` taking
the head's raw displacement back to the true one when the air is far from nominal."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import psutil
import pytest

from drivers import DeviceConnectionError, DeviceFault
from drivers.interferometer import EnvironmentReading, FeedGap, HeadOptics, create
from instrument.environment import AirConditions, wavelength_compensation
from sim_devices import World, WorldConfig
from sim_devices.ambient import AmbientModel
from sim_devices.interferometer import InterferometerTwin, move_opr

pytestmark = pytest.mark.timeout(90)

TRANSPORTS = ["socketcand", "slcan"]
CYCLES_PER_SECOND = 20.0  # the twin's and the drivers' environment_rate here, so a test waits 50 ms per cycle
FAST = {"environment_rate": CYCLES_PER_SECOND}
# Air far from nominal: a warm laboratory 800 m up. n/n_nominal − 1 ≈ −31 ppm: 2.2 µm over 70 mm.
FAR_AIR = {"air_temperature_c": 28.0, "pressure_pa": 92_000.0, "relative_humidity_percent": 30.0}
PERFECT_SENSORS = dict.fromkeys(("air_temperature_offset_std", "air_temperature_noise", "pressure_offset_std",
                                 "pressure_noise", "humidity_offset_std", "humidity_noise", "material_offset_std",
                                 "material_noise"), 0.0)


@pytest.fixture
def no_leaks():
    """Every thread and fd a test opens is closed by its fixtures."""
    process = psutil.Process()
    threads_before = {t.ident for t in threading.enumerate()}
    fds_before = process.num_fds()
    yield
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline:
        extra = [t for t in threading.enumerate() if t.ident not in threads_before and t.is_alive()]
        if not extra and process.num_fds() <= fds_before:
            break
        time.sleep(0.05)
    assert not extra, f"threads left running: {[t.name for t in extra]}"
    assert process.num_fds() <= fds_before, f"file descriptors leaked: {fds_before} -> {process.num_fds()}"


def _twin(world: World, **config) -> InterferometerTwin:
    return InterferometerTwin(world, {"layout": FAST, **config})


@pytest.fixture
def world(no_leaks):
    world = World(WorldConfig(seed=21))
    yield world
    world.truth.close()


@pytest.fixture
def twin(world):
    with _twin(world, ambient={"material_sensors": 2}) as twin:
        yield twin


def _fresh_reading(ifm, after: float | None = None, timeout: float = 10.0, strict: bool = True) -> EnvironmentReading:
    """The first reading the driver assembles after ``after`` (host clock; default now), through
    ``environment(strict=strict)``."""
    since = time.time() if after is None else after
    deadline = time.monotonic() + timeout
    while True:
        try:
            if ifm.environment(max_age=2.0, strict=False).received > since:
                return ifm.environment(max_age=2.0, strict=strict)
        except FeedGap:
            pass
        assert time.monotonic() < deadline, "no fresh environmental reading"
        time.sleep(0.01)


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_the_reading_is_the_twins_air_through_its_sensors(twin, transport):
    truth = twin.environment()
    model = AmbientModel(21, twin.config.ambient)  # the same air, computed here from the seed alone
    offsets, noise = truth["sensor_offsets"], twin.config.environment_sensors
    with create(twin.station_entry(transport), name=f"interferometer ({transport})") as ifm:
        for _ in range(3):
            reading = _fresh_reading(ifm)
            air = model.at(reading.timestamp - truth["origin"])
            # Each value: the true air plus the sensor's calibration offset, within 6 σ of its noise and
            # half a count of the field.
            assert reading.air_temperature_k == pytest.approx(
                air.air_temperature_c + offsets["air_temperature"] + 273.15, abs=6 * noise.air_temperature_noise + 5e-4)
            assert reading.pressure_pa == pytest.approx(air.pressure_pa + offsets["pressure"],
                                                        abs=6 * noise.pressure_noise + 0.5)
            humidity = (air.relative_humidity_percent + offsets["humidity"]) / 100
            assert reading.relative_humidity == pytest.approx(humidity, abs=(6 * noise.humidity_noise + 0.005) / 100)
            for index in range(2):
                assert reading.material_temperatures_k[index] == pytest.approx(
                    air.material_temperatures_c[index] + offsets[f"material{index + 1}"] + 273.15,
                    abs=6 * noise.material_noise + 5e-4)
            assert math.isnan(reading.material_temperatures_k[2])
            assert reading.material_fitted == (True, True, False) and reading.faults == ()
            assert abs(reading.received - time.time()) < 1.0
        # The sensors are not perfect: their calibration offsets show.
        assert abs(offsets["air_temperature"]) > 1e-3 and abs(offsets["pressure"]) > 0.5
        stats = ifm.stats()
        assert stats["environment_readings"] >= 3 and stats["environment_incomplete"] == 0
        assert stats["foreign_frames"] == 0


def test_a_faulty_sensor_is_a_device_fault(twin):
    with create(twin.station_entry("socketcand"), name="interferometer") as ifm:
        _fresh_reading(ifm)
        twin.sensor_fault("humidity")
        started = time.time()
        reading = _fresh_reading(ifm, after=started, strict=False)
        assert reading.faults == ("humidity",) and math.isnan(reading.relative_humidity)
        assert not math.isnan(reading.air_temperature_k) and not math.isnan(reading.pressure_pa)
        with pytest.raises(DeviceFault, match="environmental sensor fault: humidity") as caught:
            ifm.environment()
        assert caught.value.device == "interferometer" and caught.value.operation == "environment"
        assert twin.control("sensor_fault", sensor="material2") == ["humidity", "material2"]
        reading = _fresh_reading(ifm, strict=False)
        assert reading.faults == ("humidity", "material2") and reading.material_fitted == (True, True, False)
        twin.sensor_fault("humidity", faulty=False)
        twin.sensor_fault("material2", faulty=False)
        reading = _fresh_reading(ifm)
        assert reading.faults == () and 0.3 < reading.relative_humidity < 0.6
        with pytest.raises(ValueError, match="no sensor 'material3'"):
            twin.sensor_fault("material3")
    assert twin.environment()["faulty"] == []


def test_a_silent_or_absent_unit_is_a_feed_gap(twin):
    with create(twin.station_entry("socketcand"), name="interferometer") as ifm:
        _fresh_reading(ifm)
        twin.arm("stall", seconds=1.5)
        deadline = time.monotonic() + 5.0
        while True:  # three cycles (0.15 s) without a reading
            try:
                ifm.environment()
            except FeedGap as gap:
                assert "newest environmental reading is" in str(gap) and "max_age 0.15 s" in str(gap)
                break
            assert time.monotonic() < deadline, "a silent unit went unnoticed"
            time.sleep(0.02)
        _fresh_reading(ifm)  # back after the stall
    # A driver listening on other ids never hears the unit, and says so; a closed one says it is closed.
    other_ids = {**twin.station_entry("socketcand"), "layout": {**FAST, "environment_air_id": 0x391,
                                                                  "environment_material_id": 0x491}}
    with create(other_ids, name="interferometer") as ifm:
        deadline = time.monotonic() + 10.0
        while ifm.stats()["foreign_frames"] < 4:  # two cycles of the unit's frames heard, not understood
            assert time.monotonic() < deadline, "the unit's frames never arrived"
            time.sleep(0.02)
        with pytest.raises(FeedGap, match="no environmental reading received yet"):
            ifm.environment()
    with pytest.raises(DeviceConnectionError, match="closed"):
        ifm.environment(max_age=0.0)


@pytest.mark.parametrize("sensors", ["perfect", "calibrated"])
def test_compensation_gives_the_true_displacement_in_air_far_from_nominal(world, sensors):
    config = {"ambient": FAR_AIR, "scale_error": 0.0}
    if sensors == "perfect":
        config["environment_sensors"] = PERFECT_SENSORS
    with _twin(world, **config) as twin, create(twin.station_entry("socketcand"), name="interferometer") as ifm:
        assert ifm.optics == HeadOptics()  # the twin's station entry states the head's nominal air
        _fresh_reading(ifm)
        ifm.zero()
        move = 0.07  # the displacement calibration's full stroke
        move_opr(world, [move, 0.0, 0.0])
        duration = 0.2
        raw = ifm.average(duration)
        reading = ifm.environment()
        truth = twin.truth()
        true_displacement = truth["true_displacement"]  # geometric, along the (slightly tilted) beam

        optics = ifm.optics
        compensation = wavelength_compensation(
            AirConditions(reading.air_temperature_k, reading.pressure_pa, reading.relative_humidity, optics.air_co2),
            AirConditions(optics.nominal_air_temperature, optics.nominal_pressure, optics.nominal_relative_humidity,
                          optics.nominal_co2),
            optics.vacuum_wavelength)
        compensated = compensation.apply(raw)

        samples = round(duration * twin.config.layout.sample_rate)
        noise_bound = 6 * twin.config.noise_std / math.sqrt(samples) + 2 * twin.config.layout.resolution
        # The raw reading is short by the air's ppm, exactly as the twin's physics has it.
        assert raw == pytest.approx(truth["refraction_ratio"] * true_displacement, abs=noise_bound)
        assert -2.4e-6 < raw - true_displacement < -2.0e-6
        environment = twin.environment()
        if sensors == "perfect":
            # The core's Edlén and the twin's Ciddor agree within 2e-8 here; the fields' rounding adds < 3e-9.
            assert abs(1.0 / compensation.factor - environment["refraction_ratio"]) < 2e-8
            assert compensated == pytest.approx(true_displacement, abs=noise_bound + move * 2e-8)
        else:
            # Calibrated sensors leave what their offsets are worth: the compensation computed from the
            # true air differs from the one applied by exactly the error left in the displacement.
            air = environment["air"]
            from_truth = wavelength_compensation(
                AirConditions(air["air_temperature_c"] + 273.15, air["pressure_pa"],
                              air["relative_humidity_percent"] / 100.0, optics.air_co2),
                compensation.nominal, optics.vacuum_wavelength)
            left = compensated - from_truth.apply(raw)
            assert compensated - true_displacement == pytest.approx(left, abs=noise_bound + move * 2e-8)
            assert abs(left) < move * 0.5e-6  # within the XC-80 class (about 0.2 ppm at 2 σ)
        assert np.isfinite(compensated) and compensation.as_record()["factor"] == compensation.factor
