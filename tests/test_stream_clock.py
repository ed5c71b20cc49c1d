"""Camera clock → robot clock: paired timestamps (offset and drift) and motion (lag), against known truth."""

import numpy as np
import pytest

from instrument.stream import ClockError, ClockModel, estimate_clock_offset, estimate_time_lag


def test_offset_and_drift_from_paired_timestamps_with_jitter_and_outliers():
    rng = np.random.default_rng(0)
    camera = 5.0 + np.arange(600) / 200.0 + rng.normal(0, 1e-6, 600)  # 3 s of triggers at 200 Hz
    rate, offset_at_5s = 1.0 + 30e-6, 1234.5678
    jitter = 20e-6
    robot = offset_at_5s + rate * (camera - 5.0) + rng.normal(0, jitter, 600)
    robot[[17, 230, 431]] += 5e-3  # three pairs stamped late (a missed interrupt)
    camera[99] = np.nan  # one event the camera missed
    model = estimate_clock_offset(camera, robot)
    assert model.rejected == 3 and model.pairs == 596
    assert model.rate == pytest.approx(rate, abs=5 * model.rate_std)
    assert model.rate_std < 5e-6
    truth_at_reference = offset_at_5s + rate * (model.camera_reference - 5.0)
    assert model.robot_reference == pytest.approx(truth_at_reference, abs=5 * model.offset_std)
    assert model.residual_rms == pytest.approx(jitter, rel=0.15)
    assert model.to_robot(6.0) == pytest.approx(offset_at_5s + rate * 1.0, abs=1e-5)
    np.testing.assert_allclose(model.to_robot(np.array([5.0, 7.0])), [offset_at_5s, offset_at_5s + 2 * rate],
                               atol=1e-5)
    assert model.drift == pytest.approx(30e-6, abs=5 * model.rate_std)


def test_fixed_rate_and_the_trivial_models():
    camera = np.array([0.0, 1.0, 2.0])
    model = estimate_clock_offset(camera, camera + 0.25, fit_rate=False)
    assert model.rate == 1.0 and model.to_robot(10.0) == pytest.approx(10.25)
    assert ClockModel.identity().to_robot(3.5) == 3.5
    assert ClockModel.from_offset(-2.0).to_robot(3.5) == 1.5


def test_clock_errors():
    with pytest.raises(ClockError, match="pair up"):
        estimate_clock_offset([1.0, 2.0, 3.0], [1.0, 2.0])
    with pytest.raises(ClockError, match="at least 3"):
        estimate_clock_offset([1.0, np.nan, 3.0], [1.0, 2.0, 3.0])
    with pytest.raises(ClockError, match="all equal"):
        estimate_clock_offset([1.0, 1.0, 1.0], [1.0, 2.0, 3.0])


def test_lag_between_the_instrument_stream_and_the_robot_log_in_another_frame():
    """The robot logs its TCP at 500 Hz in its base frame; the instrument streams at 200 Hz in M,
    7.3 ms late on its own clock. The speed profiles agree whatever the frames."""

    def path(t):  # base frame, m: accelerate, cruise, turn, stop
        s = np.where(t < 0.5, 0.4 * t**2, 0.1 + 0.4 * (t - 0.5))
        return np.column_stack([0.4 + s, 0.1 * np.sin(3 * t), 0.3 + 0.02 * np.cos(5 * t)])

    t_robot = np.arange(0.0, 2.0, 1 / 500)
    lag = 7.3e-3
    t_measured = np.arange(0.1, 1.9, 1 / 200)  # instrument clock; t_robot = t_measured + lag
    rotation = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    measured = path(t_measured + lag) @ rotation.T + [0.2, -0.1, 0.05]
    measured += np.random.default_rng(1).normal(0, 1e-6, measured.shape)
    result = estimate_time_lag(t_measured, measured, t_robot, path(t_robot), max_lag=0.05)
    assert result.lag == pytest.approx(lag, abs=0.2e-3)
    assert result.samples > 300
    with pytest.raises(ClockError, match="max_lag"):
        estimate_time_lag(t_measured, measured, t_robot, path(t_robot), max_lag=0.0)
