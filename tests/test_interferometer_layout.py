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
from drivers.interferometer._feed import FeedBuffer
from drivers.interferometer._layout import decode_displacement, decode_reply, decode_status, encode_command
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
