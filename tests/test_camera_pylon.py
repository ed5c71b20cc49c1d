"""The pylon adapter with real pypylon against three emulated cameras serving the twin's frames."""

import cv2
import numpy as np
import pytest

from drivers import DeviceConnectionError, DeviceTimeout, SettingsError
from drivers.camera import GrabFailed, PylonCamera, PylonSettings, Roi, create, create_triplet
from sim_devices.camera import CameraFileTwin, OpticalBench
from sim_devices.world import World, WorldConfig

SERIALS = {"x": "0815-0000", "y": "0815-0001", "z": "0815-0002"}


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    world = World(WorldConfig(seed=1))
    bench = OpticalBench(world)
    twin = CameraFileTwin(world, bench, tmp_path_factory.mktemp("frames"))
    twin.start()
    yield world, bench, twin
    twin.stop()


def station_cameras(twin):
    return {k: {"adapter": "pylon", "serial": s, "emulator_image": str(twin.paths[k])} for k, s in SERIALS.items()}


@pytest.fixture
def triplet(cell):
    _, _, twin = cell
    cameras = create_triplet(station_cameras(twin))
    with cameras:
        yield cameras


def _on_disk(twin, name):
    return cv2.imread(str(twin.paths[name]), cv2.IMREAD_GRAYSCALE)


def test_three_emulated_cameras_deliver_the_rendered_frames(cell, triplet):
    world, _, twin = cell
    frames = triplet.grab()
    assert set(frames) == {"x", "y", "z"}
    for name, frame in frames.items():
        assert frame.camera == SERIALS[name] and frame.saturation == 255
        assert frame.image.shape == (1040, 1024) and frame.image.dtype == np.uint8
        np.testing.assert_array_equal(frame.image, _on_disk(twin, name))
        expected = twin.renderer.render(name, world.opr_in_m(), seq=twin.frames_written)
        np.testing.assert_array_equal(frame.image, expected)  # the known pose, pixel for pixel
    stamps = [f.timestamp for f in frames.values()]
    assert max(stamps) - min(stamps) < 1.0


def test_a_grab_after_a_settled_move_is_never_stale(cell, triplet):
    world, _, twin = cell
    previous = triplet.grab()
    rng = np.random.default_rng(0)
    for _ in range(5):
        pose = world.flange_pose()
        pose[:3, 3] += rng.uniform(-0.004, 0.004, 3)
        state = world.set_flange_pose(pose)
        frames = triplet.grab()
        for name, frame in frames.items():
            expected = twin.renderer.render(name, state.opr_in_m, seq=twin.frames_written)
            np.testing.assert_array_equal(frame.image, expected, err_msg=f"camera {name} returned a stale frame")
            assert np.any(frame.image != previous[name].image)
        previous = frames


def test_failed_buffers_are_retried_then_reported(cell, triplet):
    camera_y = triplet.cameras["y"]
    camera_y.force_failed_buffers(1)
    assert set(triplet.grab()) == {"x", "y", "z"}
    camera_y.force_failed_buffers(10)
    with pytest.raises(GrabFailed, match="camera y missing: The buffer was incompletely grabbed"):
        triplet.grab()


def test_single_camera_retries_and_configures(cell):
    _, _, twin = cell
    settings = PylonSettings(serial=SERIALS["z"], emulator_image=twin.paths["z"], retries=2, exposure_s=2e-3)
    camera = PylonCamera(settings, name="z")
    with camera:
        camera.force_failed_buffers(2)
        frame = camera.grab()
        assert frame.image.shape == (1040, 1024)
        camera.configure(roi=Roi(64, 32, 512, 480), gain_db=1.0)
        assert camera.grab().image.shape == (480, 512)


def test_a_frame_that_never_comes_times_out(cell):
    _, _, twin = cell
    # Hardware-triggered: nobody fires Line1 on the emulator, so the frame never comes.
    camera = PylonCamera(PylonSettings(serial=SERIALS["x"], emulator_image=twin.paths["x"], trigger_source="Line1",
                                       retries=1))
    with camera:
        with pytest.raises(DeviceTimeout, match="no frame within"):
            camera.grab(timeout=0.2)


def test_missing_camera_and_closed_camera_are_connection_errors(cell):
    _, _, twin = cell
    with pytest.raises(DeviceConnectionError, match="no camera with serial 0815-0099"):
        PylonCamera(PylonSettings(serial="0815-0099", emulator_image=twin.paths["x"])).open()
    camera = PylonCamera(PylonSettings(serial=SERIALS["x"], emulator_image=twin.paths["x"]))
    with pytest.raises(DeviceConnectionError, match="not open"):
        camera.grab()
    with pytest.raises(DeviceConnectionError, match="does not exist"):
        PylonCamera(PylonSettings(serial=SERIALS["x"], emulator_image=twin.paths["x"].with_name("nope.bmp"))).open()


def test_factory_takes_the_settings_model_or_a_mapping(cell):
    _, _, twin = cell
    camera = create({"adapter": "pylon", "serial": SERIALS["y"], "roi": {"offset_x": 0, "offset_y": 0, "width": 64,
                                                                         "height": 48}}, name="y")
    assert isinstance(camera, PylonCamera) and camera.name == "y" and camera.settings.roi == Roi(0, 0, 64, 48)
    assert create(PylonSettings(serial=SERIALS["y"]), name="y").settings.software_trigger
    with pytest.raises(SettingsError, match=r"^camera 'y': unknown adapter 'gige'; expected one of pylon, aravis$"):
        create({"adapter": "gige"}, name="y")
    with pytest.raises(SettingsError, match=r"^camera 'y' \(pylon\): unknown setting 'exposure'; "
                                            r"expected one of serial, emulator_image, exposure_s"):
        create({"adapter": "pylon", "serial": "1", "exposure": 1}, name="y")
    with pytest.raises(SettingsError, match=r"\(pylon\): setting 'serial' is missing"):
        create({"adapter": "pylon"}, name="y")
    with pytest.raises(SettingsError, match=r"exposure_s: input should be greater than 0 \(got -0.001\)"):
        create({"adapter": "pylon", "serial": "1", "exposure_s": -1e-3}, name="y")


def test_embedded_stamps_prove_when_the_scene_was_still_and_are_blanked(tmp_path):
    """The file twin stamps every frame it puts in place (rendered now or ahead of a move); the pylon
    adapter reads the stamp through the real emulator as the frame's exposure evidence and blanks it."""
    import time

    from drivers.camera import read_stamp

    world = World(WorldConfig(seed=2))
    twin = CameraFileTwin(world, OpticalBench(world), tmp_path / "frames", stamp_frames=True)
    twin.start()
    try:
        cameras = {k: {**v, "embedded_stamp": True} for k, v in station_cameras(twin).items()}
        with create_triplet(cameras) as triplet:
            for ahead in (False, True):
                pose = world.flange_pose()
                pose[:3, 3] += [0.003, -0.002, 0.001]
                if ahead:  # announced first: the frames are rendered ahead, then stamped when put in place
                    world.announce(flange_pose=pose)
                    time.sleep(0.5)
                before = time.time()
                state = world.set_flange_pose(pose)
                after = time.time()
                on_disk = read_stamp(_on_disk(twin, "x"))
                assert on_disk is not None and on_disk.frame_number == twin.frames_written and on_disk.still
                assert before <= on_disk.time <= after  # stamped when put in place, not when rendered
                for name, frame in triplet.grab().items():
                    assert frame.evidence == "still since" and frame.exposure_start == pytest.approx(on_disk.time)
                    expected = twin.renderer.render(name, state.opr_in_m, seq=twin.frames_written)
                    np.testing.assert_array_equal(frame.image[1:], expected[1:])
                    np.testing.assert_array_equal(frame.image[0, :24], frame.image[1, :24])  # blanked
                    np.testing.assert_array_equal(frame.image[0, 24:], expected[0, 24:])
        assert twin.stats()["rendered_ahead"] >= 1
    finally:
        twin.stop()


def test_an_emulated_frame_without_a_stamp_carries_no_evidence(cell, triplet):
    """An emulated camera serves a file's pixels: its trigger says nothing about what they show."""
    for frame in triplet.grab().values():
        assert frame.exposure_start is None and frame.evidence is None


def test_a_corrupt_or_missing_stamp_is_no_stamp():
    from drivers.camera import read_stamp
    from sim_devices.camera import stamp_image

    image = np.full((8, 64), 40, np.uint8)
    assert read_stamp(image) is None
    stamp_image(image, 7, 1234.5)
    decoded = read_stamp(image)
    assert decoded is not None and (decoded.frame_number, decoded.time, decoded.still) == (7, 1234.5, True)
    image[0, 13] ^= 0x01  # one bit of the time flipped: the CRC no longer fits
    assert read_stamp(image) is None
