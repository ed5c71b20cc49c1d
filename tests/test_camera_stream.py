"""Streaming acquisition: pylon's emulator serving a frame directory, and ``CameraTriplet.start_stream``
in the simulated cell (trigger line, camera clocks, overtrigger, frames at the truth of their instant
with motion blur), checked on the robot twin's dense truth."""

from __future__ import annotations

import os
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from drivers.camera import Roi, create, create_triplet
from drivers.robot import MotionEnvelope
from drivers.robot import create as create_robot
from instrument.pose import Geometry
from instrument.stream import PoseTracker, estimate_clock_offset
from sim_devices.camera import IDEAL_OPTICS, OpticalBench, Renderer
from sim_devices.cell import SimCell
from sim_devices.trajectory import TrajectoryLog, true_poses_in_m
from sim_devices.world import EXACT_MOUNTS, World, WorldConfig

SEED = 2


# ------------------------------------------------------------------------------------ the emulator
def _bmp(path: Path, value: int) -> None:
    cv2.imwrite(str(path), np.full((48, 64), value, np.uint8))


def test_the_emulator_serves_a_directory_in_name_order_listed_at_start_read_when_served(tmp_path):
    """What the replay of a stream relies on (pypylon's emulator, checked here): with a directory as
    ``ImageFilename`` it serves the files in name order and cycles, lists them once when
    acquisition starts (a file added later is never served) and reads each file's content when it
    serves it (a file replaced meanwhile shows its new content)."""
    _bmp(tmp_path / "single.bmp", 7)
    sequence = tmp_path / "sequence"
    sequence.mkdir()
    for i in range(3):
        _bmp(sequence / f"slot-{i:03d}.bmp", 10 * (i + 1))
    camera = create({"adapter": "pylon", "serial": "0815-0000", "emulator_image": str(tmp_path / "single.bmp")},
                    name="x")
    camera.open()
    try:
        camera.stream_begin(exposure_s=1e-3, roi=None, trigger_source="Software", sequence=sequence)

        def shot() -> tuple[int, float]:
            camera.stream_fire()
            result = camera.stream_fetch(5.0)
            assert result is not None and result[0] is not None
            return result[1], float(result[0].image.mean())

        assert [shot() for _ in range(4)] == [(0, 10.0), (1, 20.0), (2, 30.0), (3, 10.0)]
        _bmp(tmp_path / "replacement.bmp", 99)
        os.replace(tmp_path / "replacement.bmp", sequence / "slot-001.bmp")
        _bmp(sequence / "slot-003.bmp", 77)
        assert [shot() for _ in range(4)] == [(4, 99.0), (5, 30.0), (6, 10.0), (7, 99.0)]
        camera.stream_end()
        assert camera.grab().image.mean() == 7.0  # back to its single image
    finally:
        camera.close()


# ------------------------------------------------------------------------------------ the cell
class Station:
    def __init__(self, cell: SimCell) -> None:
        station = yaml.safe_load(cell.station_path.read_text())
        self.cell = cell
        self.robot = create_robot(station["devices"]["robot"],
                                  envelope=MotionEnvelope.from_dict(station["envelope"]))
        self.cameras = create_triplet(station["devices"]["cameras"])
        self.geometry = Geometry.from_dict(station["geometry"])
        self.world = World(WorldConfig.from_dict({**EXACT_MOUNTS, "seed": SEED}))
        self.truth = TrajectoryLog(cell.directory / "trajectories")
        self.streams = cell.directory / "frames" / "streams"

    def true_opr(self, times: np.ndarray) -> np.ndarray:
        flange = self.truth.flange_at(times, rest=self.world.reference_flange_pose)
        return true_poses_in_m(self.world, flange, "opr")


@pytest.fixture(scope="module")
def station():
    with SimCell(seed=SEED, time_scale=1.0, config={"optics": IDEAL_OPTICS, "world": EXACT_MOUNTS}) as cell:
        bench = Station(cell)
        bench.robot.open()
        bench.cameras.open()
        try:
            yield bench
        finally:
            bench.cameras.close()
            bench.robot.close()


def record(station: Station, rate: float, motion, *, exposure: float = 1e-3, roi: Roi | None = None,
           hold: float = 0.1):
    """Stream while ``motion()`` runs (and ``hold`` s around it); returns the stream's triples,
    its pulses' controller times and its statistics."""
    stream = station.cameras.start_stream(rate, exposure_s=exposure, roi=roi)
    with stream:
        with pytest.raises(RuntimeError, match="after stop"):
            stream.next_triple()  # the simulated line records first, replays after stop()
        time.sleep(hold)
        motion()
        time.sleep(hold)
        stream.stop()
        triples = list(stream)
        pulses = stream.sync_times()
    assert pulses is not None
    return triples, pulses, stream.stats


def test_a_stream_during_a_move_gives_the_true_pose_of_each_instant(station):
    home = station.robot.tcp_pose()
    target = home + [0.04, 0.0, 0.0, 0.0, 0.0, 0.0]
    exposure = 1e-3
    triples, pulses, stats = record(station, 100.0, lambda: station.robot.move_linear(target, 0.5, 2.5),
                                    exposure=exposure)
    station.robot.move_linear(home)
    # One triple per pulse, in order, all complete; per camera consecutive frame ids and rising stamps.
    assert stats.triggers == len(triples) == len(pulses) >= 30
    assert [t.index for t in triples] == list(range(len(triples)))
    assert stats.complete == len(triples) and sum(stats.missed.values()) == 0
    twin_clocks = station.cell.forward("cameras", "stream_stats")["clocks"]
    clocks = {}
    for camera in "xyz":
        assert [t.frame_ids[camera] for t in triples] == list(range(len(triples)))
        stamps = np.array([t.timestamps[camera] for t in triples])
        assert np.all(np.diff(stamps) > 0)
        # Paired timestamps (the pulses' controller times, the frames' mean times) give each camera's
        # clock: its rate is the twin's true drift, to the fit's own uncertainty.
        clocks[camera] = estimate_clock_offset(stamps, pulses + 0.5 * exposure)
        true_rate = 1.0 / (1.0 + twin_clocks[camera]["drift"])
        assert abs(clocks[camera].rate - true_rate) < 5 * clocks[camera].rate_std + 1e-9
        assert clocks[camera].residual_rms < 3e-6
    tracker = PoseTracker(station.geometry, clock=clocks)
    for t in triples:
        tracker.add(t.index, t.timestamps, {k: f.image for k, f in t.frames.items()})
    poses = tracker.stream()
    assert poses.dropped == 0 and len(poses.time) == len(triples)
    truth = station.true_opr(poses.time)[:, :3, 3]
    error = np.linalg.norm(poses.raw[:, :3] - truth, axis=1)
    travelled = np.linalg.norm(truth - truth[0], axis=1)
    assert np.ptp(travelled) > 0.039  # the stream saw the whole move
    # Each frame shows the pose of its instant: moving, the error is the static one (the vision's
    # noise, ≈ 2.5 µm RMS on these 1 MP frames), where the truth one frame period away is millimetres off.
    speed = np.r_[0.0, np.linalg.norm(np.diff(truth, axis=0), axis=1) / np.diff(poses.time)]
    moving, resting = speed > 0.05, speed < 1e-3
    assert np.sum(moving) >= 15 and np.sum(resting) >= 15
    rms_moving, rms_resting = (float(np.sqrt(np.mean(error[m] ** 2))) for m in (moving, resting))
    assert rms_moving < 1.5 * rms_resting + 0.5e-6 and rms_moving < 4e-6 and np.max(error) < 8e-6
    a_frame_off = station.true_opr(poses.time + 0.01)[:, :3, 3]
    assert np.min(np.linalg.norm(poses.raw[moving, :3] - a_frame_off[moving], axis=1)) > 100e-6


def test_frames_during_fast_motion_are_blurred_over_their_exposure(station):
    home = station.robot.tcp_pose()
    target = home + [0.0, 0.05, 0.0, 0.0, 0.0, 0.0]
    exposure = 2e-3
    triples, pulses, _ = record(station, 50.0, lambda: station.robot.move_linear(target, 0.5, 2.5),
                                exposure=exposure)
    station.robot.move_linear(home)
    start = pulses + 0.0  # the twin's trigger delay is 0: exposures start at the pulses
    speeds = [np.linalg.norm(np.diff(station.true_opr(np.array([s, s + exposure]))[:, :3, 3], axis=0)) / exposure
              for s in start]
    fastest = int(np.argmax(speeds))
    assert speeds[fastest] > 0.25
    # Two noise-free references at the truth of that exposure: sharp at its middle pose, and the
    # mean over 24 instants of it. The streamed frame is the blurred one, not the sharp one.
    world = World(WorldConfig.from_dict({**EXACT_MOUNTS, "seed": SEED}))
    renderer = Renderer(OpticalBench(world, IDEAL_OPTICS), seed=SEED, bit_depth=8)
    instants = start[fastest] + (np.arange(24) + 0.5) / 24 * exposure
    middle = station.true_opr(np.array([start[fastest] + 0.5 * exposure]))[0]
    scale = exposure / 1e-3
    for camera in "xyz":
        image = triples[fastest].frames[camera].image.astype(float)
        sharp = renderer.render(camera, middle, noise=False, quantise=False, exposure_scale=scale)
        blurred = renderer.render(camera, middle, noise=False, quantise=False, exposure_scale=scale,
                                  blur=list(station.true_opr(instants)))
        stripes = (np.abs(sharp - blurred) > 5.0) & (np.maximum(sharp, blurred) < 250)
        if np.sum(stripes) < 200:
            continue  # this camera's stripes run along the motion: no visible blur
        miss_sharp = np.sqrt(np.mean((image[stripes] - sharp[stripes]) ** 2))
        miss_blurred = np.sqrt(np.mean((image[stripes] - blurred[stripes]) ** 2))
        assert miss_blurred < 0.7 * miss_sharp, camera
        break
    else:
        pytest.fail("no camera shows the motion")


def test_a_rate_too_high_for_the_readout_misses_pulses_counts_them_and_fills_nothing(station):
    # A full frame (1040 rows × 4.8 µs) takes 5 ms to read out: at 250 pulses/s every other one
    # comes while the camera is busy. With a 400-row ROI (1.9 ms) every pulse is taken.
    triples, pulses, stats = record(station, 250.0, lambda: None, hold=0.1)
    assert stats.triggers == len(triples) == len(pulses) >= 40
    for camera in "xyz":
        have = [t.index for t in triples if camera in t.frames]
        assert have == list(range(0, len(triples), 2))
        assert stats.missed[camera] == len(triples) - len(have) and stats.frames[camera] == len(have)
        assert [t.frame_ids[camera] for t in triples if camera in t.frames] == list(range(len(have)))
        for t in triples:
            if camera not in t.frames:
                assert camera not in t.timestamps and "trigger missed" in t.missing[camera]
    assert stats.complete == len(have)
    triples, _, stats = record(station, 250.0, lambda: None, roi=Roi(0, 300, 1024, 400), hold=0.1)
    assert stats.complete == len(triples) and sum(stats.missed.values()) == 0
    assert triples[0].frames["x"].image.shape == (400, 1024)


def test_closing_a_stream_releases_the_cameras_and_the_recording(station):
    stream = station.cameras.start_stream(100.0, exposure_s=1e-3, roi=Roi(0, 0, 512, 512))
    time.sleep(0.05)
    stream.stop()
    first = stream.next_triple()
    assert first is not None and first.frames["y"].image.shape == (512, 512)
    stream.close()  # before the end: the rest is dropped
    deadline = time.monotonic() + 5.0
    while any(station.streams.iterdir()):
        assert time.monotonic() < deadline, f"left behind: {sorted(station.streams.iterdir())}"
        time.sleep(0.02)
    frames = station.cameras.grab()  # single grabs again, full sensor
    assert all(f.image.shape == (1040, 1024) for f in frames.values())
    with pytest.raises(ValueError, match="rate"):
        station.cameras.start_stream(0.0)
