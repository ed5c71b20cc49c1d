"""The CAN interferometer adapter against its twin, with the real python-can client over both
transports (socketcand over loopback TCP, slcan over a pty): readings against the world's truth,
and every fault giving a typed error, no hang and no wrong value."""

import math
import re
import socket
import threading
import time

import numpy as np
import psutil
import pytest

from drivers import DeviceConnectionError, DeviceError, DeviceTimeout, ProtocolError
from drivers.interferometer import BeamInterrupted, CanInterferometer, DatumLost, FeedGap, create
from sim_devices import TwinProcess, World, WorldConfig
from sim_devices.interferometer import InterferometerTwin, InterferometerTwinConfig, move_opr

pytestmark = pytest.mark.timeout(60)

TRANSPORTS = ["socketcand", "slcan"]
AXES = {"x": 0, "y": 1, "z": 2}
# |n/n_nominal − 1| in the default ambient: ±0.55 K (0.53 ppm), ±3.5 hPa (0.94 ppm), 41..49 % RH.
AIR_BOUND = 2e-6


# ------------------------------------------------------------------------------------ fixtures
@pytest.fixture
def no_leaks():
    """Every thread, socket and pty fd opened by a test is closed by its fixtures."""
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


@pytest.fixture
def world(no_leaks):
    world = World(WorldConfig(seed=11))
    yield world
    world.truth.close()


@pytest.fixture
def twin(world):
    with InterferometerTwin(world) as twin:
        yield twin


@pytest.fixture(params=TRANSPORTS)
def ifm(request, twin):
    device = create(twin.station_entry(request.param), name=f"interferometer ({request.param})")
    with device:
        _wait_for_sample(device)
        yield device


def _wait_for_sample(device, timeout=5.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            device.latest(max_age=2.0)
            return True
        except FeedGap:
            time.sleep(0.01)
    raise AssertionError("no sample from the twin within 5 s")


def _arm_later(twin, delay, kind, **params):
    """Arm a fault ``delay`` seconds from now (inside an averaging window that is running)."""
    timer = threading.Timer(delay, lambda: twin.faults.arm(kind, **params))
    timer.start()
    return timer


def _wait_until(predicate, timeout=5.0, what="condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


def _fault_during_average(device, twin, kind, error, match, attempts=3, **params):
    """Arm ``kind`` 0.1 s into a 1 s average and return the error it raised, checked against
    ``error``/``match``. On a starved host the slcan feed (host-stamped) may report a stall before
    the fault fires (conservative, and still a ``FeedGap``); then wait the fault out and try again."""
    for _attempt in range(attempts):
        device.zero()
        timer = _arm_later(twin, 0.1, kind, **params)
        started = time.monotonic()
        try:
            device.average(1.0)
        except DeviceError as exc:
            caught = exc
        else:
            raise AssertionError(f"{kind} did not disturb the average")
        finally:
            timer.join()
        assert time.monotonic() - started < 5.0  # fails at the fault, no hang
        if isinstance(caught, error) and re.search(match, str(caught)):
            return caught
        assert isinstance(caught, FeedGap) and "stalled" in str(caught), caught
        time.sleep(float(params.get("seconds", 0.0)) + 0.2)
        _wait_until(lambda: device.latest(max_age=2.0).beam_ok, what="beam back")
    raise AssertionError(f"{kind} never showed as {match!r} in {attempts} attempts; last: {caught}")


def _average_when_recovered(device, duration=0.1, timeout=10.0):
    """Average once the feed is usable again (after a fault has passed)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return device.average(duration)
        except (FeedGap, DeviceConnectionError, DeviceTimeout):  # DeviceTimeout: a starved host's backlog
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


# ------------------------------------------------------------------------------------ accuracy
@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_reading_matches_world_truth_along_each_axis(twin, ifm, world, axis):
    config: InterferometerTwinConfig = twin.config
    twin.align(axis)
    ifm.zero()
    start = world.opr_in_m()[:3, 3]
    distance = {"x": 0.05, "y": -0.03, "z": 0.02}[axis]
    delta = np.zeros(3)
    delta[AXES[axis]] = distance
    move_opr(world, delta)
    try:
        duration = 0.1
        measured = _average_when_recovered(ifm, duration)
        moved = world.opr_in_m()[:3, 3] - start
        samples = round(duration * config.layout.sample_rate)
        noise_bound = 6 * config.noise_std / math.sqrt(samples) + 2 * config.layout.resolution

        # Independent of the twin's internals: the nominal axis, bounded by the head's spec.
        # Error = d (cos θ - 1) + scale d + air d + u_perp · lateral; θ within 5 σ per tilt component;
        # the default ambient keeps n/n_nominal within AIR_BOUND of 1.
        theta = 5 * math.sqrt(2) * config.misalignment_std
        along = moved[AXES[axis]]
        lateral = float(np.linalg.norm(np.delete(moved, AXES[axis])))
        bound = abs(along) * (config.scale_error_limit + AIR_BOUND + theta**2 / 2) + theta * lateral + noise_bound
        assert abs(measured - along) <= bound, (measured, along, bound)

        # Tight: with the head's true beam direction, scale error and air, only noise and rounding remain.
        truth = twin.truth()
        scale = (1 + truth["scale_error"]) * truth["refraction_ratio"]
        expected = scale * float(np.dot(truth["beam_direction"], moved))
        assert abs(measured - expected) <= noise_bound, (measured, expected, noise_bound)
        assert ifm.status().axis == axis
    finally:
        move_opr(world, -delta)


def test_latest_sample_and_health_counters(twin, ifm):
    ifm.zero()
    sample = ifm.latest(max_age=2.0)
    assert sample.beam_ok and sample.datum_set and not math.isnan(sample.displacement)
    assert abs(sample.displacement) < 20e-9  # only noise after the datum
    assert 0.9 <= sample.signal_strength <= 1.0
    assert sample.received >= sample.timestamp - 0.01
    stats = ifm.stats()
    assert stats["connected"] and stats["samples"] > 0 and stats["protocol_errors"] == 0
    seen = list(zip(range(300), ifm.samples(timeout=1.0)))
    counters = [s.counter for _, s in seen]
    assert all((b - a) % 256 == 1 for a, b in zip(counters, counters[1:]))


# ------------------------------------------------------------------------------------ datum
def test_no_datum_means_no_number(twin, ifm):
    twin.align("y")  # re-aiming loses the count
    _wait_until(lambda: not ifm.latest(max_age=2.0).datum_set, what="datum lost")
    assert math.isnan(ifm.latest(max_age=2.0).displacement)
    with pytest.raises(DatumLost, match="zero"):
        ifm.average(0.05)
    with pytest.raises(DatumLost):
        ifm.latest_valid(max_age=2.0)
    ifm.zero()
    assert abs(_average_when_recovered(ifm, 0.05)) < 20e-9


# ------------------------------------------------------------------------------------ faults
def test_beam_break_is_reported_and_loses_the_datum(twin, ifm):
    caught = _fault_during_average(ifm, twin, "beam_break", BeamInterrupted, "beam not OK", seconds=0.5)
    assert not isinstance(caught, DatumLost)
    assert not ifm.latest(max_age=2.0).beam_ok
    with pytest.raises(BeamInterrupted, match="refused"):
        ifm.zero()  # the head will not set a datum without the beam
    _wait_until(lambda: ifm.latest(max_age=2.0).beam_ok, what="beam back")
    with pytest.raises(DatumLost):
        ifm.average(0.05)  # the count was lost with the beam
    ifm.zero()
    assert abs(_average_when_recovered(ifm, 0.05)) < 20e-9


def test_stall_is_a_feed_gap(twin, ifm):
    if ifm.stats()["transport"] == "socketcand":
        # A short stall: the feed resumes inside the window with a contiguous counter; the jump in
        # the head's timestamps shows it. (slcan frames carry host timestamps: a reader backlog
        # can hide a short pause there; no sample is lost by it.)
        _fault_during_average(ifm, twin, "stall", FeedGap, "stalled", seconds=0.4)
    # A long one: the average gives up waiting, latest() reports the newest sample as old.
    ifm.zero()
    timer = _arm_later(twin, 0.1, "stall", seconds=2.0)
    started = time.monotonic()
    try:
        with pytest.raises(FeedGap, match="no sample received"):
            ifm.average(3.0)
        assert time.monotonic() - started < 2.0
        with pytest.raises(FeedGap, match="old"):
            ifm.latest(max_age=0.1)
    finally:
        timer.join()
    assert abs(_average_when_recovered(ifm)) < 20e-9  # a stall does not lose the count


def test_dropped_frames_are_a_counter_gap(twin, ifm):
    lost_before = ifm.stats()["lost_samples"]
    _fault_during_average(ifm, twin, "drop_reply", FeedGap, r"3 sample\(s\) missing", frames=3)
    assert ifm.stats()["lost_samples"] - lost_before >= 3
    assert abs(_average_when_recovered(ifm, 0.05)) < 20e-9


def test_bad_crc_is_a_counted_protocol_error(twin, ifm):
    _fault_during_average(ifm, twin, "bad_crc", FeedGap, "CRC mismatch", frames=2)
    errors = ifm.protocol_errors()
    crc_errors = [e for e in errors if isinstance(e, ProtocolError) and "CRC" in e.cause]
    assert len(crc_errors) >= 2
    assert ifm.stats()["protocol_errors"] >= 2
    assert abs(_average_when_recovered(ifm, 0.05)) < 20e-9


def test_garbage_on_the_line_is_rejected_and_the_feed_recovers(twin, ifm):
    _fault_during_average(ifm, twin, "garbage", FeedGap, "rejected|missing|connection", size=24)
    assert ifm.stats()["garbage_reads"] >= 1
    assert any("undecodable" in e.cause for e in ifm.protocol_errors())
    assert abs(_average_when_recovered(ifm)) < 20e-9


def test_disconnect_is_reported_then_the_driver_reconnects(twin, ifm):
    ifm.zero()
    timer = _arm_later(twin, 0.1, "disconnect", seconds=0.5)
    started = time.monotonic()
    try:
        with pytest.raises((FeedGap, DeviceConnectionError)):
            ifm.average(1.5)
        assert time.monotonic() - started < 5.0
    finally:
        timer.join()
    assert abs(_average_when_recovered(ifm)) < 20e-9  # the head kept its datum; only the link dropped
    assert ifm.stats()["reconnects"] >= 1


# ------------------------------------------------------------------------------------ opening
def test_open_fails_fast_with_a_typed_error(no_leaks, tmp_path):
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        free_port = probe.getsockname()[1]
    started = time.monotonic()
    for config in ({"adapter": "socketcand", "host": "127.0.0.1", "port": free_port, "open_attempts": 2},
                   {"adapter": "slcan", "port": str(tmp_path / "no-such-tty"), "open_attempts": 2}):
        with pytest.raises(DeviceConnectionError, match="could not open") as caught:
            create(config, name="ifm").open()
        assert caught.value.device == "ifm" and caught.value.operation == "open"
    assert time.monotonic() - started < 10.0


def test_socketcand_handshake_race_is_retried(world):
    """With no pause after the rawmode ``< ok >`` the first frame can share the client's read and
    python-can rejects the handshake; the driver's retries still get the bus open."""
    with InterferometerTwin(world, {"first_frame_pause": 0.0, "slcan": False}) as twin:
        for _ in range(3):
            with create({**twin.station_entry(), "open_attempts": 10}, name="ifm") as ifm:
                _wait_for_sample(ifm)


@pytest.fixture
def resource_tracker_running():
    """multiprocessing keeps one pipe to its resource tracker for the life of the test process;
    start it before ``no_leaks`` counts file descriptors."""
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()


def test_twin_in_its_own_process(resource_tracker_running, no_leaks):
    """The standalone host in a spawned process, driven through TwinProcess, over both transports."""
    with TwinProcess("sim_devices.interferometer:StandaloneInterferometerHost", {"seed": 5}) as proc:
        endpoints = proc.endpoints
        configs = [{"adapter": "socketcand", **endpoints["socketcand"]},
                   {"adapter": "slcan", "port": endpoints["slcan"]["port"]}]
        proc.call("align", axis="z")
        for config in configs:
            with create(config, name="ifm") as ifm:
                _wait_for_sample(ifm)
                ifm.zero()
                before = np.array(proc.call("opr_in_m"))[:3, 3]
                after = np.array(proc.call("move_opr", delta=[0.0, 0.0, 0.04]))[:3, 3]
                measured = _average_when_recovered(ifm, 0.1)
                truth = proc.call("truth")
                expected = (1 + truth["scale_error"]) * truth["refraction_ratio"] * float(
                    np.dot(truth["beam_direction"], after - before))
                assert abs(measured - expected) < 5e-9
                proc.call("move_opr", delta=[0.0, 0.0, -0.04])
        assert proc.call("stats")["commands"] >= 4


def test_driver_never_leaks_a_sample_without_a_valid_value(twin, ifm):
    """During a beam break every sample handed out has NaN displacement and beam_ok False."""
    ifm.zero()
    twin.faults.arm("beam_break", seconds=0.3)
    seen = []
    for sample in ifm.samples(timeout=1.0):
        seen.append(sample)
        if len(seen) >= 500:
            break
    bad = [s for s in seen if not (s.beam_ok and s.datum_set)]
    assert bad, "the beam break never showed"
    assert all(math.isnan(s.displacement) for s in bad)
    assert all(not math.isnan(s.displacement) for s in seen if s.beam_ok and s.datum_set)


def test_driver_is_an_interferometer(twin):
    from drivers.interferometer import Interferometer

    device = create(twin.station_entry("socketcand"), name="ifm")
    assert isinstance(device, Interferometer) and isinstance(device, CanInterferometer)
    assert issubclass(FeedGap, DeviceError) and issubclass(BeamInterrupted, DeviceError)
