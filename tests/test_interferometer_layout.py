"""Frame layout, CRC, the twin's encoder against the driver's decoder, and the feed buffer's rules
(no I/O: fast)."""

import math
import time

import pytest

from drivers import DeviceConnectionError, ProtocolError, SettingsError
from drivers.interferometer import (
    BeamInterrupted,
    CanInterferometer,
    CanSample,
    DatumLost,
    FeedGap,
    FrameLayout,
    SlcanSettings,
    crc8_j1850,
    create,
)
from drivers.interferometer._environment import EnvironmentTracker
from drivers.interferometer._feed import FeedBuffer
from drivers.interferometer._layout import (
    decode_displacement,
    decode_environment_air,
    decode_environment_material,
    decode_reply,
    decode_status,
    encode_command,
)
from sim_devices.interferometer import _frames

LAYOUT = FrameLayout()

# The worked example of docs/interferometer.md: +12.3456789 mm, counter 42, beam OK + datum set,
# signal 14/15, on id 0x181.
# 123456789 = 0x075BCD15 (little-endian in bytes 0..4); status 0x05 | 14 << 4 = 0xE5; CRC 0xEE.
DOC_EXAMPLE = bytes.fromhex("15CD5B07002AE5EE")


def test_crc8_j1850_check_values():
    assert crc8_j1850(b"123456789") == 0x4B  # the catalogue check value of CRC-8/SAE-J1850
    assert _frames.crc8(b"123456789") == 0x4B  # the twin's own (table-driven) implementation


def test_documented_example_frame_decodes():
    data = DOC_EXAMPLE
    frame = decode_displacement("ifm", 0x181, data)
    assert frame.counts == 123_456_789
    assert frame.counts * LAYOUT.resolution == pytest.approx(12.3456789e-3, abs=1e-13)
    assert (frame.counter, frame.beam_ok, frame.datum_set, frame.signal_low, frame.overrange) == (42, True, True,
                                                                                                 False, False)
    assert frame.signal_strength == pytest.approx(14 / 15)
    # and the twin encodes exactly these bytes
    assert _frames.displacement_frame(0x181, 123_456_789, 42, _frames.BEAM_OK | _frames.DATUM_SET, 14 / 15) == data


@pytest.mark.parametrize("counts", [0, 1, -1, 2**39 - 1, -(2**39 - 1), -123_456_789_012])
def test_twin_encoder_and_driver_decoder_agree(counts):
    data = _frames.displacement_frame(0x181, counts, 255, _frames.BEAM_OK, 0.5)
    frame = decode_displacement("ifm", 0x181, data)
    assert frame.counts == counts and frame.counter == 255 and frame.beam_ok and not frame.datum_set


def test_status_reply_and_command_frames_round_trip():
    status = decode_status("ifm", 0x281, _frames.status_frame(0x281, _frames.BEAM_OK, 0.75, "z", 7, 200))
    assert (status.axis, status.datum_generation, status.heartbeat) == ("z", 7, 200)
    assert status.signal_strength == pytest.approx(0.75, abs=1e-4)
    reply = decode_reply("ifm", 0x581, _frames.reply_frame(0x581, 1, 33, 1, 9))
    assert (reply.opcode, reply.token, reply.result, reply.datum_generation) == (1, 33, 1, 9)
    assert _frames.parse_command(0x601, encode_command(0x601, 1, 17)) == (1, 17)
    assert _frames.parse_command(0x602, encode_command(0x601, 1, 17)) is None  # the id is in the CRC


def test_corrupt_frames_are_protocol_errors():
    good = _frames.displacement_frame(0x181, 1000, 3, _frames.BEAM_OK, 1.0)
    with pytest.raises(ProtocolError, match="CRC mismatch"):
        decode_displacement("ifm", 0x181, good[:7] + bytes([good[7] ^ 1]))
    with pytest.raises(ProtocolError, match="CRC mismatch"):
        decode_displacement("ifm", 0x181, bytes([good[0] ^ 0x10]) + good[1:])
    with pytest.raises(ProtocolError, match="5 data bytes"):
        decode_displacement("ifm", 0x181, good[:5])


# The worked example of docs/interferometer.md for the environmental unit: cycle 5, air 20.000 °C
# (20000 = 0x4E20), 101 325 Pa (41325 = 0xA16D above 60 kPa), 50.00 % RH (5000 = 0x1388); one material
# sensor at 20.500 °C (0x5014), two not fitted (0xFFFF).
DOC_AIR = bytes.fromhex("204E6DA1881350EA")
DOC_MATERIAL = bytes.fromhex("1450FFFFFFFF505A")


def test_documented_environment_frames_decode():
    air = decode_environment_air("ifm", 0x381, DOC_AIR)
    assert (air.air_temperature_k, air.pressure_pa, air.relative_humidity) == (293.15, 101325.0, 0.5)
    assert (air.faults, air.counter) == ((), 5)
    material = decode_environment_material("ifm", 0x481, DOC_MATERIAL)
    assert material.temperatures_k[0] == 293.65 and all(math.isnan(t) for t in material.temperatures_k[1:])
    assert (material.fitted, material.faults, material.counter) == ((True, False, False), (), 5)
    # and the twin encodes exactly these bytes
    assert _frames.environment_frames(0x381, 0x481, 5, 20.0, 101325.0, 50.0, [20.5], set()) == [
        (0x381, DOC_AIR), (0x481, DOC_MATERIAL)]


def test_environment_faults_and_ranges_round_trip():
    frames = dict(_frames.environment_frames(0x381, 0x481, 21, 19.9996, 101_324.6, 45.678, [20.1, 70.0],
                                             {"pressure"}))
    air = decode_environment_air("ifm", 0x381, frames[0x381])
    assert air.air_temperature_k == pytest.approx(293.15 - 0.0004, abs=0.5e-3)  # 1 mK steps
    assert math.isnan(air.pressure_pa) and air.faults == ("pressure",)
    assert air.relative_humidity == pytest.approx(0.45678, abs=0.5e-4) and air.counter == 21 % 16
    material = decode_environment_material("ifm", 0x481, frames[0x481])
    # 70 °C is beyond the field (0..65.534 °C): no reading, and the sensor says so.
    assert material.temperatures_k[0] == pytest.approx(293.25) and math.isnan(material.temperatures_k[1])
    assert material.fitted == (True, True, False) and material.faults == ("material2",)
    with pytest.raises(ProtocolError, match="CRC mismatch"):
        decode_environment_air("ifm", 0x381, DOC_AIR[:7] + bytes([DOC_AIR[7] ^ 1]))
    with pytest.raises(ProtocolError, match="CRC mismatch"):  # the id is in the CRC
        decode_environment_material("ifm", 0x481, DOC_AIR)


def test_a_reading_needs_both_frames_of_one_cycle():
    tracker = EnvironmentTracker()
    air = decode_environment_air("ifm", 0x381, DOC_AIR)
    material = decode_environment_material("ifm", 0x481, DOC_MATERIAL)
    assert tracker.newest() == (None, math.inf)
    assert tracker.on_material(material, 1.0) == (False, 0)  # no air frame for this cycle
    tracker.on_air(air)
    assert tracker.on_material(material, 2.0) == (True, 0)
    reading, age = tracker.newest()
    assert reading is not None and reading.timestamp == 2.0 and reading.counter == 5 and age < 1.0
    assert reading.material_temperatures_k[0] == 293.65 and reading.relative_humidity == 0.5
    # A cycle whose air frame was lost leaves the previous reading in place; the next complete one counts the gap.
    later = dict(_frames.environment_frames(0x381, 0x481, 8, 21.0, 101000.0, 40.0, [], set()))
    tracker.on_air(decode_environment_air("ifm", 0x381, later[0x381]))
    assert tracker.on_material(decode_environment_material("ifm", 0x481, DOC_MATERIAL), 3.0) == (False, 0)
    tracker.on_air(decode_environment_air("ifm", 0x381, later[0x381]))
    assert tracker.on_material(decode_environment_material("ifm", 0x481, later[0x481]), 4.0) == (True, 2)
    newest, _ = tracker.newest()
    assert newest is not None and newest.air_temperature_k == 294.15 and newest.material_fitted == (False,) * 3


def test_layout_is_data_validated_by_its_model():
    layout = FrameLayout.model_validate({"displacement_id": "0x185", "resolution": 1e-12})
    assert layout.displacement_id == 0x185 and layout.resolution == 1e-12 and layout.status_id == 0x281
    assert FrameLayout.model_validate(layout.model_dump()) == layout
    with pytest.raises(ValueError, match="displacment_id"):
        FrameLayout.model_validate({"displacment_id": 1})
    with pytest.raises(ValueError, match="11-bit"):
        FrameLayout(displacement_id=0x800)
    with pytest.raises(ValueError, match="must differ"):
        FrameLayout(status_id=0x181)
    with pytest.raises(ValueError, match="status_rate 2000.0 Hz is above sample_rate"):
        FrameLayout(status_rate=2000.0)
    with pytest.raises(ValueError, match="is not a number"):
        FrameLayout.model_validate({"reply_id": "0xZZ"})
    with pytest.raises(ValueError, match="must differ"):
        FrameLayout(environment_material_id=0x381)
    with pytest.raises(ValueError, match="environment_rate 2000.0 Hz is above sample_rate"):
        FrameLayout(environment_rate=2000.0)
    assert FrameLayout.model_validate({"environment_air_id": "0x391"}).environment_air_id == 0x391


def test_the_heads_optics_are_settings_in_si():
    settings = SlcanSettings(port="/dev/null", optics={"nominal_pressure": 100_000.0})
    assert settings.optics.nominal_pressure == 100_000.0 and settings.optics.vacuum_wavelength == 632.991e-9
    assert (settings.optics.nominal_air_temperature, settings.optics.nominal_relative_humidity) == (293.15, 0.5)
    with pytest.raises(SettingsError, match="nominal_relative_humidity"):
        create({"adapter": "slcan", "port": "/dev/null", "optics": {"nominal_relative_humidity": 50.0}})
    with pytest.raises(SettingsError, match="vacuum_wavelength"):
        create({"adapter": "slcan", "port": "/dev/null", "optics": {"vacuum_wavelength": 633.0}})


def test_create_rejects_bad_configs_clearly():
    with pytest.raises(SettingsError, match=r"^interferometer 'ifm': unknown adapter 'vcan'; "
                                            r"expected one of socketcand, slcan$"):
        create({"adapter": "vcan"}, name="ifm")
    with pytest.raises(SettingsError, match=r"\(socketcand\): setting 'port' is missing"):
        create({"adapter": "socketcand", "host": "127.0.0.1"}, name="ifm")
    with pytest.raises(SettingsError, match=r"\(slcan\): unknown setting 'host'; expected one of port, bitrate, lay"):
        create({"adapter": "slcan", "port": "/dev/null", "host": "x"}, name="ifm")
    with pytest.raises(SettingsError, match=r"layout.sample_rate: input should be greater than 0 \(got -1\)"):
        create({"adapter": "slcan", "port": "/dev/null", "layout": {"sample_rate": -1}}, name="ifm")
    with pytest.raises(SettingsError, match="8-bit sample counter could wrap"):
        create({"adapter": "slcan", "port": "/dev/null", "stall_timeout": 0.3}, name="ifm")
    ifm = create(SlcanSettings(port="/nonexistent/tty", layout=FrameLayout(sample_rate=500.0)), name="ifm")
    assert isinstance(ifm, CanInterferometer) and ifm.stall_timeout == pytest.approx(0.4)  # 200 sample periods
    with pytest.raises(DeviceConnectionError, match="not open"):
        ifm.average(0.1)


# ------------------------------------------------------------------------------------ feed buffer
def _sample(counter, displacement=1e-6, beam_ok=True, datum_set=True, defect=""):
    valid = beam_ok and datum_set
    return CanSample(timestamp=time.time(), displacement=displacement if valid else math.nan, beam_ok=beam_ok,
                     signal_strength=0.9, counter=counter, received=time.time(), datum_set=datum_set,
                     signal_low=False, overrange=False, defect=defect)


def _buffer_with(samples):
    buffer = FeedBuffer(64, "ifm")
    for sample in samples:
        buffer.push(sample)
    return buffer


def _average(buffer, count):
    return buffer.average(count, time.monotonic() + 0.2, 0.2, "average", start=0)


def test_average_of_contiguous_samples():
    buffer = _buffer_with([_sample(i, displacement=i * 1e-9) for i in range(10)])
    assert _average(buffer, 10) == pytest.approx(4.5e-9)


def test_a_gap_inside_the_window_is_never_averaged_over():
    samples = [_sample(i) for i in range(5)] + [_sample(8, defect="2 sample(s) missing (counter 4 -> 8)")]
    with pytest.raises(FeedGap, match="2 sample"):
        _average(_buffer_with(samples), 6)
    # a defect before the window (on its first sample) does not concern the window
    assert _average(_buffer_with(samples[5:] + [_sample(9)]), 2) == pytest.approx(1e-6)


def test_beam_and_datum_problems_raise_typed_errors():
    with pytest.raises(BeamInterrupted, match="beam not OK"):
        _average(_buffer_with([_sample(0), _sample(1, beam_ok=False)]), 2)
    with pytest.raises(DatumLost, match="zero"):
        _average(_buffer_with([_sample(0, datum_set=False)]), 1)
    assert issubclass(DatumLost, BeamInterrupted)


def test_missing_samples_time_out_as_feed_gap():
    buffer = _buffer_with([_sample(0)])
    started = time.monotonic()
    with pytest.raises(FeedGap, match="no sample"):
        buffer.average(5, time.monotonic() + 0.2, 0.1, "average", start=0)
    assert time.monotonic() - started < 2.0
