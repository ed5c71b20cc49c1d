"""Camera file twin, SimCamera and CameraTriplet without pypylon."""

import time

import cv2
import numpy as np
import pytest

from drivers import DeviceConnectionError, DeviceTimeout
from drivers.camera import Camera, CameraTriplet, GrabFailed, Roi, TriggeredCamera, create
from sim_devices.camera import CameraFileTwin, OpticalBench, SimCamera
from sim_devices.faults import FaultKind, FaultPlan
from sim_devices.world import World, WorldConfig


@pytest.fixture
def world():
    return World(WorldConfig(seed=2))


@pytest.fixture
def bench(world):
    return OpticalBench(world)


def _moved(world, dx):
    pose = world.flange_pose()
    pose[:3, 3] += dx
    return pose


def test_file_twin_writes_the_settled_pose_before_the_setter_returns(world, bench, tmp_path):
    twin = CameraFileTwin(world, bench, tmp_path)
    twin.start()
    try:
        assert all(p.is_file() for p in twin.paths.values())
        state = world.set_flange_pose(_moved(world, [0.01, 0.02, 0.0]))
        for name, path in twin.paths.items():
            on_disk = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            expected = twin.renderer.render(name, state.opr_in_m, seq=twin.frames_written)
            np.testing.assert_array_equal(on_disk, expected)
        frames = world.truth.entries("frames")
        assert frames[-1]["seq"] == state.seq
        np.testing.assert_allclose(frames[-1]["opr_in_m"]["t"], state.opr_in_m[:3, 3])
        # a moving (unsettled) state leaves the files alone
        before = {n: p.stat().st_mtime_ns for n, p in twin.paths.items()}
        world.set_flange_pose(_moved(world, [0.0, 0.01, 0.0]), settled=False)
        assert {n: p.stat().st_mtime_ns for n, p in twin.paths.items()} == before
        assert not list(tmp_path.glob(".*.tmp"))  # no temporary file left behind
        twin.control("laser", on=False)
        dark = cv2.imread(str(twin.paths["x"]), cv2.IMREAD_GRAYSCALE)
        assert dark.max() < 40
    finally:
        twin.stop()
    seq = len(world.truth.entries("frames"))
    world.set_flange_pose(_moved(world, [0.0, 0.0, 0.01]))
    assert len(world.truth.entries("frames")) == seq  # unsubscribed


def test_an_announced_pose_is_rendered_ahead_and_put_in_place_when_it_settles(world, bench, tmp_path):
    twin = CameraFileTwin(world, bench, tmp_path)
    twin.start()
    try:
        target = _moved(world, [0.004, -0.002, 0.001])
        world.announce(flange_pose=target)
        deadline = time.monotonic() + 20.0
        while not list(tmp_path.glob(".x.ahead-*.bmp")) or twin._ahead_frames.state != "done":
            assert time.monotonic() < deadline, "the announced frames were never rendered"
            time.sleep(0.01)
        state = world.set_flange_pose(target)
        assert twin.stats() == {"frames_written": 2, "announced": 1, "rendered_ahead": 1}
        for name, path in twin.paths.items():
            expected = twin.renderer.render(name, state.opr_in_m, seq=twin.frames_written)
            np.testing.assert_array_equal(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE), expected)
        # An announcement that does not come true is not used, and its frames do not stay behind.
        world.announce(flange_pose=_moved(world, [0.01, 0.0, 0.0]))
        state = world.set_flange_pose(_moved(world, [0.0, 0.01, 0.0]))
        assert twin.stats()["announced"] == 1 and twin.frames_written == 3
        expected = twin.renderer.render("z", state.opr_in_m, seq=3)
        np.testing.assert_array_equal(cv2.imread(str(twin.paths["z"]), cv2.IMREAD_GRAYSCALE), expected)
    finally:
        twin.stop()
    assert not list(tmp_path.glob(".*.bmp"))


def test_sim_camera_implements_the_protocol_and_follows_the_world(world, bench):
    camera = SimCamera(world, bench, "z")
    assert isinstance(camera, Camera) and isinstance(camera, TriggeredCamera)
    with pytest.raises(DeviceConnectionError, match="not open"):
        camera.grab()
    with camera:
        first = camera.grab()
        world.set_flange_pose(_moved(world, [0.02, 0.0, 0.0]))
        second = camera.grab()
        assert second.frame_id == first.frame_id + 1 and second.saturation == 255
        assert np.abs(first.image.astype(int) - second.image.astype(int)).max() > 100  # the cross moved
        camera.configure(pixel_format="Mono12", roi=Roi(100, 200, 300, 400))
        deep = camera.grab()
        assert deep.image.dtype == np.uint16 and deep.image.shape == (400, 300) and deep.saturation == 4095


def test_sim_camera_faults_become_typed_errors(world, bench):
    faults = FaultPlan()
    with SimCamera(world, bench, "x", faults=faults, retries=2) as camera:
        faults.arm(FaultKind.DROP_REPLY, count=2)
        assert camera.grab().image.shape == (1040, 1024)  # two incomplete buffers, third attempt works
        faults.arm(FaultKind.DROP_REPLY, count=3)
        with pytest.raises(GrabFailed, match="incompletely grabbed"):
            camera.grab()
        faults.arm(FaultKind.STALL, count=-1)
        with pytest.raises(DeviceTimeout):
            camera.grab(timeout=0.05)
        faults.clear()
        faults.arm(FaultKind.DISCONNECT)
        with pytest.raises(DeviceConnectionError, match="removed"):
            camera.grab()


def test_triplet_returns_three_frames_or_names_the_missing_camera(world, bench):
    faults = {name: FaultPlan() for name in "xyz"}
    cameras = {name: SimCamera(world, bench, name, faults=faults[name]) for name in "xyz"}
    with CameraTriplet(cameras, retries=1) as triplet:
        frames = triplet.grab()
        assert set(frames) == {"x", "y", "z"}
        assert max(f.timestamp for f in frames.values()) - min(f.timestamp for f in frames.values()) < 1.0
        faults["y"].arm(FaultKind.DROP_REPLY, count=1)
        assert set(triplet.grab()) == {"x", "y", "z"}  # retried as a set
        faults["y"].arm(FaultKind.DROP_REPLY, count=-1)
        with pytest.raises(GrabFailed, match="camera y missing"):
            triplet.grab()
        faults["y"].clear()
        faults["z"].arm(FaultKind.STALL, count=-1)
        with pytest.raises(DeviceTimeout, match="camera z missing"):
            triplet.grab(timeout=0.05)


def test_factory_rejects_bad_config():
    with pytest.raises(ValueError, match="unknown adapter"):
        create({"adapter": "gige"}, name="x")
    with pytest.raises(ValueError, match="unknown setting"):
        create({"adapter": "pylon", "serial": "1", "exposure": 1}, name="x")
    camera = create({"adapter": "pylon", "serial": "0815-0000"}, name="x")
    assert camera.name == "x" and isinstance(camera, TriggeredCamera)
