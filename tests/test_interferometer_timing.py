"""Timestamps and real gaps in the interferometer feed, and the slcan twin's folder after SIGKILL.

The socketcand twin forwards receive timestamps (send time, bus time, kernel latency), as the real
daemon forwards the kernel's, so the driver's timestamp-based stall check is exercised here by a
twin that really stops sending (``stall``) and by one whose frames are held up on the way and then
arrive in a burst (``delay``): the first is a gap on both transports, the second only where the
timestamps are the host's own (slcan).
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import numpy as np
import pytest

from drivers.interferometer import CanSample, create
from sim_devices import World, WorldConfig
from sim_devices.interferometer import (
    SLCAN_FOLDER_PREFIX,
    CanBusTiming,
    InterferometerTwin,
    remove_stale_slcan_folders,
)

pytestmark = pytest.mark.timeout(90)

ROOT = Path(__file__).resolve().parents[1]
DISPLACEMENT_ID, REPLY_ID, COMMAND_ID = 0x181, 0x581, 0x601
STALL_TIMEOUT = 0.2  # the driver's default: 200 sample periods at 1 kHz


@pytest.fixture
def twin() -> Iterator[InterferometerTwin]:
    world = World(WorldConfig(seed=21))
    with InterferometerTwin(world) as twin:
        yield twin
    world.truth.close()


@pytest.fixture(params=["socketcand", "slcan"])
def feed(request, twin):
    device = create(twin.station_entry(request.param), name=f"ifm ({request.param})")
    with device:
        deadline = time.monotonic() + 5.0
        while not device.recent(1):
            assert time.monotonic() < deadline, "no sample within 5 s"
            time.sleep(0.01)
        yield request.param, device


def _collect_once(device, seconds: float, during) -> list[CanSample]:
    samples: list[CanSample] = []
    end = time.monotonic() + seconds
    for sample in device.samples(timeout=2.0):
        samples.append(sample)
        if during is not None and len(samples) == 50:
            during()
        if time.monotonic() >= end:
            return samples
    raise AssertionError("the feed ended")


def _collect(device, seconds: float, during=None, twin: InterferometerTwin | None = None) -> list[CanSample]:
    """Every sample for ``seconds`` from now on; ``during()`` runs once the collection has begun.

    With ``twin``: tried again (up to 3 times) if the twin itself skipped samples meanwhile, i.e. a
    host so starved that the twin's clock fell more than its catch-up limit behind."""
    for _attempt in range(3):
        skipped = twin.stats()["late_skipped"] if twin is not None else 0
        samples = _collect_once(device, seconds, during)
        if twin is None or twin.stats()["late_skipped"] == skipped:
            return samples
        time.sleep(0.5)  # let a fault armed by ``during`` run out
    raise AssertionError("the host starved the twin in every attempt")


def _silence(defect: str) -> float:
    found = re.search(r"no sample for ([0-9.]+) s \(feed stalled\)", defect)
    return float(found.group(1)) if found else 0.0


def _contiguous(samples: list[CanSample]) -> bool:
    return all((b.counter - a.counter) % 256 == 1 for a, b in zip(samples, samples[1:]))


# ------------------------------------------------------------------------------ receive timestamps
def test_bus_timing_stamps_when_sent_and_spreads_what_the_bus_cannot_carry_at_once():
    timing = CanBusTiming(np.random.default_rng(3), bitrate=1_000_000, rx_latency=20e-6)
    sent = 1_700_000_000.0
    paced = [timing.receive_time(sent + k * 1e-3, 8) for k in range(200)]  # one frame per ms: the bus is free
    delays = np.array(paced) - (sent + np.arange(200) * 1e-3)
    assert np.all(delays >= 5e-6) and np.all(delays <= 5e-6 + 50 * 20e-6)  # only the kernel's latency
    assert float(np.mean(delays)) == pytest.approx(25e-6, rel=0.3)
    assert delays.std() > 0
    burst = [timing.receive_time(sent + 1.0, 8) for _ in range(200)]  # all handed over at once: they queue
    assert all(b > a for a, b in zip(burst, burst[1:]))
    # An 8-byte standard frame is 111..135 bits plus 3 of interframe space: 126 bits on average, 126 µs at 1 Mbit/s.
    assert (burst[-1] - burst[0]) / 199 == pytest.approx(126e-6, rel=0.05)
    again = CanBusTiming(np.random.default_rng(3), bitrate=1_000_000, rx_latency=20e-6)
    assert [again.receive_time(sent + k * 1e-3, 8) for k in range(200)] == paced  # seeded


def test_socketcand_forwards_receive_times_not_ideal_due_times(twin):
    bus = can.Bus(interface="socketcand", **{k: v for k, v in twin.station_entry("socketcand").items()
                                             if k != "adapter"})
    try:
        frames: list[tuple[can.Message, float]] = []
        token = 77
        deadline = time.monotonic() + 1.0
        sent_command = False
        while time.monotonic() < deadline:
            message = bus.recv(timeout=0.1)
            if message is not None:
                frames.append((message, time.time()))
            if not sent_command and len(frames) > 100:
                data = bytes([2, token, 0, 0, 0, 0, 0])  # sync; the twin ignores a bad CRC: compute it
                bus.send(can.Message(arbitration_id=COMMAND_ID, data=data + bytes([_crc(COMMAND_ID, data)]),
                                     is_extended_id=False))
                sent_command = True
    finally:
        bus.shutdown()
    stamps = [m.timestamp for m, _ in frames]
    assert all(b > a for a, b in zip(stamps, stamps[1:])), "timestamps must increase in bus order"
    assert all(abs(m.timestamp - arrived) < 1.0 for m, arrived in frames)  # epoch seconds, this host's clock
    samples = [m.timestamp for m, _ in frames if m.arbitration_id == DISPLACEMENT_ID]
    intervals = np.diff(samples)
    assert len(intervals) > 300
    # Not the ideal 1 ms grid: the twin's real send times vary, and so does the bus.
    assert len({round(i * 1e6) for i in intervals}) > 20
    assert abs(float(np.median(intervals)) - 1e-3) < 0.2e-3
    replies = [i for i, (m, _) in enumerate(frames) if m.arbitration_id == REPLY_ID and m.data[1] == token]
    assert replies, "no reply to the sync command"
    after = next(m for m, _ in frames[replies[0] + 1:] if m.arbitration_id == DISPLACEMENT_ID)
    reply = frames[replies[0]][0]
    assert after.timestamp > reply.timestamp  # each frame its own slot on the bus: no shared stamp


def _crc(can_id: int, body: bytes) -> int:
    """CRC-8/SAE-J1850 over the id (2 bytes big-endian) and the body (docs/interferometer.md)."""
    crc = 0xFF
    for byte in can_id.to_bytes(2, "big") + body:
        for bit in range(7, -1, -1):
            top = (crc >> 7) ^ (byte >> bit & 1)
            crc = (crc << 1) & 0xFF
            if top:
                crc ^= 0x1D
    return crc ^ 0xFF


# ------------------------------------------------------------------------------ real gaps
def test_a_real_stall_is_a_gap_on_its_timestamps(twin, feed):
    transport, device = feed
    stalls_before = device.stats()["stalls"]
    # 0.6 s: slcan's stamps are the host's read times, and a host thread that is itself late by up to
    # 0.4 s (a loaded machine) still sees more than the 0.2 s limit of silence.
    samples = _collect(device, 1.5, during=lambda: twin.arm("stall", seconds=0.6), twin=twin)
    assert _contiguous(samples)  # the head's counter stops with it: only the silence shows
    stalled = [(a, b) for a, b in zip(samples, samples[1:]) if "stalled" in b.defect]
    assert len(stalled) >= 1 and device.stats()["stalls"] - stalls_before >= len(stalled)
    before, after = max(stalled, key=lambda pair: _silence(pair[1].defect))
    assert _silence(after.defect) >= 0.3
    if transport == "socketcand":
        # measured on the head's receive timestamps, which really jump by the stall
        assert after.timestamp - before.timestamp == pytest.approx(_silence(after.defect), abs=1e-3)
        # and every verdict follows the timestamps: stalled exactly where they jump by more than the limit
        for a, b in zip(samples, samples[1:]):
            assert ("stalled" in b.defect) == (b.timestamp - a.timestamp > STALL_TIMEOUT), (a, b)


def test_a_short_stall_is_seen_in_the_timestamps_but_is_no_gap(twin):
    """socketcand only: slcan frames carry the host's read time, not the head's (see the test above)."""
    with create(twin.station_entry("socketcand"), name="ifm") as device:
        samples = _collect(device, 0.8, during=lambda: twin.arm("stall", seconds=0.08), twin=twin)
    assert _contiguous(samples)
    jumps = [b.timestamp - a.timestamp for a, b in zip(samples, samples[1:])]
    assert max(jumps) >= 0.08  # the silence is there
    for a, b in zip(samples, samples[1:]):  # and reported only if it (with the twin's lateness) passed 0.2 s
        assert ("stalled" in b.defect) == (b.timestamp - a.timestamp > STALL_TIMEOUT), (a, b)


def test_frames_held_up_on_the_way_are_no_gap_where_the_timestamps_are_the_devices(twin, feed):
    transport, device = feed
    samples = _collect(device, 1.2, during=lambda: twin.arm("delay", seconds=0.35), twin=twin)
    assert _contiguous(samples)  # nothing lost: every frame came, late
    pairs = list(zip(samples, samples[1:]))
    arrival_gap = max(b.received - a.received for a, b in pairs)
    assert arrival_gap >= 0.3  # they really were held
    if transport == "socketcand":
        # the burst carries receive timestamps: contiguous, so no stall however late they came
        held = max(pairs, key=lambda pair: pair[1].received - pair[0].received)
        assert held[1].timestamp - held[0].timestamp < STALL_TIMEOUT
        for a, b in pairs:
            assert ("stalled" in b.defect) == (b.timestamp - a.timestamp > STALL_TIMEOUT), (a, b)
    else:
        # python-can stamps slcan frames when it reads them: the pause is all the driver can see
        assert any("stalled" in b.defect for _, b in pairs)


# ------------------------------------------------------------------------------ the slcan folder
_TWIN_SCRIPT = """
import json, sys, time
from sim_devices import World, WorldConfig
from sim_devices.interferometer import InterferometerTwin
twin = InterferometerTwin(World(WorldConfig(seed=1)), {"socketcand": False})
print(json.dumps(twin.start()["slcan"]), flush=True)
time.sleep(120)
"""


@pytest.fixture
def twin_processes() -> Iterator[Callable[[], tuple[subprocess.Popen, str]]]:
    """Twins in processes of their own: ``(process, slcan folder)``; each is killed at the end."""
    started: list[tuple[subprocess.Popen, str]] = []

    def start() -> tuple[subprocess.Popen, str]:
        process = subprocess.Popen([sys.executable, "-c", _TWIN_SCRIPT], cwd=ROOT, stdout=subprocess.PIPE,
                                   stderr=subprocess.DEVNULL, text=True)
        line: list[str] = []
        reader = threading.Thread(target=lambda: line.append(process.stdout.readline()), daemon=True)
        reader.start()
        reader.join(60.0)
        assert line and line[0], "the twin process did not start"
        entry = (process, os.path.dirname(json.loads(line[0])["port"]))
        started.append(entry)
        return entry

    yield start
    for process, _ in started:
        if process.poll() is None:
            process.kill()
        process.wait(10.0)
        process.stdout.close()


def test_a_killed_twins_slcan_folder_is_removed_by_the_next_twin(twin_processes, tmp_path):
    killed, killed_folder = twin_processes()
    alive, alive_folder = twin_processes()
    assert os.path.basename(killed_folder).startswith(SLCAN_FOLDER_PREFIX)
    killed.send_signal(signal.SIGKILL)
    killed.wait(10.0)
    assert os.path.isdir(killed_folder)  # SIGKILL leaves no chance to clean up ...
    world = World(WorldConfig(seed=2))
    with InterferometerTwin(world, {"socketcand": False}) as twin:  # ... the next twin does it
        own_folder = os.path.dirname(twin.endpoints["slcan"]["port"])
        assert not os.path.exists(killed_folder)
        assert os.path.isdir(alive_folder) and os.path.isdir(own_folder)  # live ones are left alone
        assert remove_stale_slcan_folders() == []
    world.truth.close()
    assert not os.path.exists(own_folder)  # stop() removes its own
    # A folder that is not a twin's (no lock file) is never touched.
    stranger = tmp_path / f"{SLCAN_FOLDER_PREFIX}someone-else"
    stranger.mkdir()
    assert remove_stale_slcan_folders(str(tmp_path)) == [] and stranger.is_dir()
