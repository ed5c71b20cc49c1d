"""instrument.stream: frame triples → timestamped poses, against the poses the crosses came from.

Crosses come from the exact forward model (``predict_measurements``) for a known trajectory, or
from images rendered from those crosses (tests/synthetic_cross.py) for the tracker. Every trigger
either gives a sample or is counted as dropped with its reason; no row is ever made up.
"""

import numpy as np
import pytest

from instrument.pose import Geometry, Pose, predict_measurements, tool_pose
from instrument.stream import ClockModel, Drop, FrameTriple, PoseSample, PoseStreamer, PoseTracker
from tests.synthetic_cross import render_cross
from tests.test_pose_station import AWKWARD_CAMERAS, station_dict

GEOMETRY = Geometry.from_dict(station_dict(AWKWARD_CAMERAS))
RATE = 200.0  # Hz, trigger rate


def trajectory(k):
    """A smooth 6-DOF motion: pose of trigger k."""
    t = k / RATE
    translation = [0.01 * np.sin(2 * t), -0.008 * np.cos(3 * t), 0.004 * t]
    euler = np.radians([0.3 * np.sin(t), -0.2 * t, 0.4 * np.cos(1.5 * t)])
    return Pose.from_euler(translation, euler)


def triple(k, *, offset=0.0, crosses=None):
    stamp = k / RATE + offset
    return FrameTriple(
        k, {"x": stamp, "y": stamp + 2e-6, "z": stamp - 3e-6},
        crosses if crosses is not None else predict_measurements(trajectory(k), GEOMETRY),
    )


def test_poses_times_and_quality_of_a_clean_stream():
    streamer = PoseStreamer(GEOMETRY, clock=ClockModel.from_offset(100.0))
    for k in range(40):
        sample = streamer.add(triple(k))
        assert isinstance(sample, PoseSample)
        truth = trajectory(k)
        np.testing.assert_allclose(sample.raw[:3], truth.translation, atol=1e-9)
        np.testing.assert_allclose(sample.raw[3:], truth.euler, atol=1e-9)
        assert sample.time == pytest.approx(100.0 + k / RATE - 1e-6 / 3, abs=1e-12)
        assert sample.timestamp_spread == pytest.approx(5e-6, abs=1e-12)
        assert sample.residual_rms < 1e-9 and sample.min_sections >= 8 and sample.tracked == 0
    stream = streamer.stream()
    assert len(stream) == 40 and stream.dropped == 0 and stream.drops == ()
    np.testing.assert_array_equal(stream.index, np.arange(40))
    assert np.all(np.diff(stream.time) > 0)
    np.testing.assert_array_equal(stream.pose, stream.raw)  # no compensation, no tool
    assert stream.positions.shape == (40, 3)
    assert stream.sample(5).index == 5


def test_compensation_then_tool_transform_are_applied():
    shift = np.array([1e-5, -2e-5, 3e-5, 1e-6, 0.0, -2e-6])
    calls = []

    def compensate(raw):
        calls.append(raw.copy())
        return raw - shift

    tool = Pose.from_euler([0.01, 0.02, 0.15], np.radians([0.0, 5.0, 0.0]))
    streamer = PoseStreamer(GEOMETRY, compensate=compensate, tool_in_opr=tool)
    sample = streamer.add(triple(3))
    np.testing.assert_allclose(calls[0], sample.raw)
    expected = tool_pose(Pose.from_iso(sample.raw - shift), tool).as_iso()
    np.testing.assert_allclose(sample.pose, expected, atol=1e-15)


def test_every_lost_trigger_is_counted_with_its_reason_and_nothing_is_interpolated():
    streamer = PoseStreamer(GEOMETRY)
    other = predict_measurements(trajectory(500), GEOMETRY)
    results = {}
    for k in (0, 1, 2, 5, 6, 7, 8, 9, 10, 4, 11):  # 3 and 4 not received; 4 arrives late
        t = triple(k)
        if k == 6:
            t = triple(k, crosses={**t.crosses, "y": None})
            t = FrameTriple(t.index, t.timestamps, t.crosses, {"y": "only one stripe found (near-vertical)"})
        if k == 7:  # the z frame is from another instant: the crosses cannot come from one pose
            t = triple(k, crosses={**t.crosses, "z": other["z"]})
        if k == 8:
            t = FrameTriple(8, {"x": 0.04, "y": 0.04, "z": 0.0455}, t.crosses)
        results[k] = streamer.add(t)
    stream = streamer.stream()
    assert isinstance(results[6], Drop) and "screen y: only one stripe found" in results[6].reason
    assert isinstance(results[7], Drop) and results[7].reason.startswith("pose: the three crosses do not come")
    assert isinstance(results[8], Drop) and "timestamps differ by 5.500 ms" in results[8].reason
    assert isinstance(results[4], Drop) and "out of order" in results[4].reason
    not_received = [d for d in stream.drops if d.reason == "not received"]
    assert [(d.index, d.count) for d in not_received] == [(3, 2)]
    np.testing.assert_array_equal(stream.index, [0, 1, 2, 5, 9, 10, 11])
    assert stream.dropped == 2 + 1 + 1 + 1 + 1  # 3–4 lost, 6, 7, 8, the late 4
    for i, k in enumerate(stream.index):  # the samples after the drops are still exact
        np.testing.assert_allclose(stream.raw[i, :3], trajectory(k).translation, atol=1e-9)
    assert streamer.samples == 7 and streamer.dropped == stream.dropped


def test_each_camera_on_its_own_clock():
    clocks = {"x": ClockModel.from_offset(10.0), "y": ClockModel(0.0, 10.0005, 1.0), "z": ClockModel.from_offset(9.999)}
    streamer = PoseStreamer(GEOMETRY, clock=clocks, max_timestamp_spread=2e-3)
    sample = streamer.add(triple(0))
    assert sample.time == pytest.approx(np.mean([10.0, 10.0005 + 2e-6, 9.999 - 3e-6]), abs=1e-12)
    assert sample.timestamp_spread == pytest.approx(1.5e-3 + 5e-6, abs=1e-12)
    with pytest.raises(TypeError, match="clock"):
        PoseStreamer(GEOMETRY, clock={"x": ClockModel()})


def frames_of(pose, seed, missing_vertical_on=None):
    """Images (1040 × 1024, 8-bit) of the three crosses a pose puts on the screens."""
    images = {}
    for i, (name, m) in enumerate(predict_measurements(pose, GEOMETRY).items()):
        img, _ = render_cross((1040, 1024), tuple(m.center), m.angle, m.perpendicularity, sigma=2.0,
                              amplitude=180.0, noise=2.0, seed=seed * 3 + i, vertical=name != missing_vertical_on)
        images[name] = img
    return images


def test_tracker_follows_the_crosses_from_frame_to_frame():
    tracker = PoseTracker(GEOMETRY)
    errors = []
    for k in range(6):
        truth = Pose.from_euler([0.002 + 2e-4 * k, -0.001, 0.0005 * k], np.radians([0.1, -0.05 * k, 0.02]))
        sample = tracker.add(k, dict.fromkeys("xyz", k / RATE), frames_of(truth, seed=k))
        assert isinstance(sample, PoseSample), sample
        assert sample.tracked == (0 if k == 0 else 3)
        errors.append([*(sample.raw[:3] - truth.translation), *(sample.raw[3:] - truth.euler)])
    errors = np.abs(np.array(errors))
    # synthetic crosses are straight lines through the whole frame (the forward model's ~1e-4 px
    # curvature from perspective is not drawn): a few µm and arc-seconds at 0.156 mm/px
    assert errors[:, :3].max() < 5e-6 and np.degrees(errors[:, 3:].max()) * 3600 < 5.0
    assert tracker.fallbacks == 0


def test_tracker_drops_a_frame_without_a_cross_and_recovers():
    tracker = PoseTracker(GEOMETRY)
    pose = Pose.from_euler([0.001, 0.0, 0.0], np.zeros(3))
    assert isinstance(tracker.add(0, dict.fromkeys("xyz", 0.0), frames_of(pose, 1)), PoseSample)
    drop = tracker.add(1, dict.fromkeys("xyz", 0.005), frames_of(pose, 2, missing_vertical_on="y"))
    # (camera y is turned by −128°: its lone stripe runs near the image diagonal, where the full
    # search may take it for both stripes and then finds no usable sections — an error either way)
    assert isinstance(drop, Drop) and drop.reason.startswith("cross missing — screen y: ")
    again = tracker.add(2, dict.fromkeys("xyz", 0.010), frames_of(pose, 3))
    assert isinstance(again, PoseSample) and again.tracked == 2  # y found by the full search again
    assert tracker.stream().dropped == 1
