"""The Aravis adapter against the GigE Vision twin (another process) and against Aravis's own fake camera.

What is checked against the truth: the frames are pixel-exact the renderer's image of the twin's
true pose (same seed, the frame's noise seq from the twin's record), in Mono8, Mono12 and Mono16,
full frame and ROI; dropped packets are resent and the frame still exact; a camera that stops
answering becomes a typed error; three cameras on one action command expose together.
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import time

import numpy as np
import pytest

from drivers import DeviceConnectionError, DeviceTimeout, SettingsError
from drivers.camera import AravisCamera, AravisSettings, CameraTriplet, Roi, aravis_available, create
from tests._gige import Truth, gige_twins, record_of

WHY_NOT = aravis_available()
pytestmark = [pytest.mark.timeout(120),
              pytest.mark.skipif(WHY_NOT is not None, reason=f"Aravis cannot be used here: {WHY_NOT}")]


@pytest.fixture(scope="module")
def truth() -> Truth:
    return Truth()


@pytest.fixture(scope="module")
def twin_x():
    with gige_twins("x") as (twin,):
        yield twin


def test_settings_need_one_address_and_create_builds_the_aravis_adapter():
    with pytest.raises(SettingsError, match="exactly one"):
        create({"adapter": "aravis"}, name="x")
    with pytest.raises(SettingsError):
        create({"adapter": "aravis", "address": "127.0.0.1", "trigger_source": "Line"}, name="x")
    camera = create({"adapter": "aravis", "address": "127.0.0.1", "packet_size": 9000}, name="x")
    assert isinstance(camera, AravisCamera) and not camera.is_open


def test_a_grab_is_the_renderers_frame_in_every_pixel_format_and_roi(twin_x, truth):
    camera = AravisCamera(AravisSettings(address=twin_x.endpoints["host"], exposure_s=1e-3), name="x")
    with camera:
        frame = camera.grab(5.0)
        record = record_of(twin_x, frame.frame_id)
        assert frame.image.shape == (1040, 1024) and frame.image.dtype == np.uint8 and frame.saturation == 255
        assert np.array_equal(frame.image, truth.frame(record))
        assert record["source"] == "Software"
        for pixel_format, dtype, saturation in (("Mono12", np.uint16, 4095), ("Mono16", np.uint16, 65535)):
            camera.configure(pixel_format=pixel_format, roi=Roi(104, 200, 320, 320))
            frame = camera.grab(5.0)
            record = record_of(twin_x, frame.frame_id)
            assert frame.image.shape == (320, 320) and frame.image.dtype == dtype
            assert frame.saturation == saturation and record["roi"] == [104, 200, 320, 320]
            assert np.array_equal(frame.image, truth.frame(record)), pixel_format
        assert frame.image.max() > 0.5 * saturation  # the cross is in this window, bright
        camera.configure(pixel_format="Mono8", roi=Roi(0, 0, 1024, 1040))


def test_dropped_packets_are_resent_and_the_frame_is_whole_with_jumbo_packets(twin_x, truth):
    settings = AravisSettings(address=twin_x.endpoints["host"], packet_timeout_s=0.005, packet_size=9000)
    with AravisCamera(settings, name="x") as camera:
        before = twin_x.call("stats")["channel"]
        twin_x.call("drop_packets", fraction=0.02, seed=7)
        try:
            frames = [camera.grab(5.0) for _ in range(3)]
        finally:
            twin_x.call("clear_faults")
        after = twin_x.call("stats")["channel"]
        # 9000-byte datagrams carry 8964 bytes of image each: 119 payload packets + leader + trailer a frame.
        blocks = after["blocks"] - before["blocks"]  # ≥ 3: a frame that stayed incomplete is grabbed again
        assert blocks >= 3
        assert (after["packets"] + after["dropped"] - before["packets"] - before["dropped"]) == blocks * 121
        dropped = after["dropped"] - before["dropped"]
        assert dropped > 0 and after["resent"] - before["resent"] >= dropped
        assert camera.statistics()["resent_packets"] >= dropped
        for frame in frames:
            assert np.array_equal(frame.image, truth.frame(record_of(twin_x, frame.frame_id)))


def test_a_frame_that_comes_after_its_grab_timed_out_is_never_the_next_grabs(twin_x, truth):
    with AravisCamera(AravisSettings(address=twin_x.endpoints["host"], retries=0), name="x") as camera:
        # The first frame leaves the camera 0.5 s late: its grab gives up at 0.2 s, and the second grab
        # is waiting when it arrives. Exposed before the second trigger, it must not be taken for its frame.
        twin_x.call("late_frames", delay=0.5, count=1)
        with pytest.raises(DeviceTimeout):
            camera.grab(0.2)
        frame = camera.grab(5.0)
        first, second = twin_x.call("frames", last=2)
        assert frame.frame_id == second["block_id"] != first["block_id"]
        assert camera.stray_buffers >= 1  # the late frame came during the wait and was put back
        assert np.array_equal(frame.image, truth.frame(second))


def test_a_camera_that_stops_answering_is_a_typed_error_then_control_is_lost():
    with gige_twins("y") as (twin,):
        camera = AravisCamera(AravisSettings(address=twin.endpoints["host"], timeout_s=1.0, retries=0), name="y")
        with camera:
            camera.grab(5.0)
            twin.call("unresponsive")
            with pytest.raises(DeviceTimeout):  # the trigger's GVCP write is never acknowledged
                camera.grab(1.0)
            deadline = time.monotonic() + 20.0  # Aravis's heartbeat: every 1 s, gives up after 5 s of retries
            while True:
                try:
                    camera.retrieve(0.5)
                except DeviceConnectionError as error:
                    assert "control lost" in str(error)
                    break
                except DeviceTimeout:
                    pass
                assert time.monotonic() < deadline, "the lost camera was never reported as lost"
        twin.call("clear_faults")
        assert twin.call("stats")["control_lost"] >= 1  # the twin dropped its controller too


def test_one_action_command_exposes_three_cameras_together(truth):
    with gige_twins("xyz") as twins:
        action = {"device_key": 0x1234, "group_key": 7, "group_mask": 1}
        cameras = {name: AravisCamera(AravisSettings(address=twin.endpoints["host"], trigger_source="Action1",
                                                     action=action, roi=Roi(360, 360, 320, 320)), name=name)
                   for name, twin in zip("xyz", twins)}
        with CameraTriplet(cameras) as triplet:
            for _ in range(2):
                frames = triplet.grab(5.0)
                records = {name: record_of(twin, frames[name].frame_id) for name, twin in zip("xyz", twins)}
                assert {r["source"] for r in records.values()} == {"Action1"}
                for name, record in records.items():
                    assert np.array_equal(frames[name].image, truth.frame(record)), name
        # Each twin exposed once per grab: one action round fired all three.
        assert [twin.call("stats")["exposed"] for twin in twins] == [2, 2, 2]


@pytest.fixture()
def fake_camera():
    """Aravis's own fake GigE Vision camera on a free loopback address (started and stopped here)."""
    binary = shutil.which("arv-fake-gv-camera-0.8")
    if binary is None:
        pytest.skip("arv-fake-gv-camera-0.8 is not installed (Debian's aravis-tools)")
    # The fake serves only on an address a network interface has: here 127.0.0.1 (lo), not the block
    # of SIM_LOOPBACK_BLOCK. It is skipped when another fake (or twin) holds 127.0.0.1:3956.
    host = "127.0.0.1"
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.bind((host, 3956))
    except OSError:
        pytest.skip("UDP 127.0.0.1:3956 is in use: Aravis's fake camera cannot serve there now")
    finally:
        probe.close()
    process = subprocess.Popen([binary, "-i", host, "-s", "TEST0"], stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)
    try:
        time.sleep(0.5)
        assert process.poll() is None, "the fake camera did not start"
        yield host
    finally:
        process.terminate()
        try:
            process.wait(5.0)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(5.0)


def test_the_adapter_drives_aravis_own_fake_camera(fake_camera):
    settings = AravisSettings(address=fake_camera, exposure_s=2e-3, roi=Roi(0, 0, 256, 128))
    with AravisCamera(settings, name="fake") as camera:
        first = camera.grab(5.0)
        second = camera.grab(5.0)
        assert first.image.shape == (128, 256) and first.image.dtype == np.uint8
        assert second.frame_id > first.frame_id and first.image.any()
        camera.configure(pixel_format="Mono16")
        frame = camera.grab(5.0)
        assert frame.image.dtype == np.uint16 and frame.saturation == 65535
