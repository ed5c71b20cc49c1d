import numpy as np
import pytest

from drivers import MotionRefused
from drivers.robot import MotionEnvelope


@pytest.fixture
def envelope():
    return MotionEnvelope(
        box_min=np.array([0.3, -0.3, 0.2]),
        box_max=np.array([0.7, 0.3, 0.6]),
        reference_rotvec=np.array([np.pi, 0, 0]),
        max_tilt=np.radians(10),
        max_speed=0.5,
    )


def test_inside_passes(envelope):
    envelope.check_pose(np.array([0.5, 0.0, 0.4, np.pi, 0, 0]))


def test_outside_box_names_axis_and_limits(envelope):
    with pytest.raises(MotionRefused, match=r"TCP z = 650\.000 mm is outside the envelope \[200\.000, 600\.000\] mm"):
        envelope.check_pose(np.array([0.5, 0.0, 0.65, np.pi, 0, 0]))


def test_tilt_refused(envelope):
    with pytest.raises(MotionRefused, match="orientation is 20"):
        envelope.check_pose(np.array([0.5, 0.0, 0.4, np.pi - np.radians(20), 0, 0]))


def test_bad_numbers_and_speeds(envelope):
    with pytest.raises(MotionRefused, match="6 finite numbers"):
        envelope.check_pose(np.array([np.nan, 0, 0, 0, 0, 0]))
    with pytest.raises(MotionRefused, match="speed 0.8"):
        envelope.check_speed(0.8, 1.0)
    with pytest.raises(MotionRefused, match="acceleration"):
        envelope.check_speed(0.1, -1.0)


def test_error_names_device_operation_cause(envelope):
    with pytest.raises(MotionRefused) as info:
        envelope.check_pose(np.array([0.9, 0, 0.4, np.pi, 0, 0]), device="robot ur5e")
    assert info.value.device == "robot ur5e" and info.value.operation == "check target"
    assert "x = 900.000 mm" in info.value.cause
