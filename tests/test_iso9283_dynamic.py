"""ISO 9283 dynamic characteristics against synthetic trajectories with analytically known values.

- a damped oscillation about the attained position (the step response of a second-order system):
  overshoot A·exp(−ζπ/√(1−ζ²)), stabilisation time from the last crossing of the band (a root of
  the analytic curve, found by bracketing, not by the code under test);
- a move at constant acceleration then a decaying residual oscillation: departure at
  sqrt(2·band/a), settling at the last root of the residual oscillation against the band;
- paths with a known offset (straight line shifted across, circle of the wrong radius);
- a corner rounded by an arc of radius r (CR = r/cos(φ/2) − r) with a decaying bump after it;
- a speed profile v_c·(1 + ε_j) + δ·sin(2πft) with known mean, spread and fluctuation.
"""

import numpy as np
import pytest
from scipy.optimize import brentq

from instrument.iso9283 import (
    CommandPath,
    ISO9283Error,
    circular_path,
    corner_deviation,
    linear_path,
    minimum_positioning_time,
    path_characteristics,
    path_speed,
    path_velocity,
    pose_stabilisation,
    positioning_time,
)

U = np.array([2.0, -1.0, 2.0]) / 3.0  # approach direction (unit)
TARGET = np.array([0.41, -0.07, 0.33])  # attained position, m


def step_response(tau, amplitude, frequency, zeta):
    """Position along the approach (m, < 0 short of the target) τ s after the signal."""
    omega = 2 * np.pi * frequency
    sigma, omega_d = zeta * omega, omega * np.sqrt(1 - zeta**2)
    return -amplitude * np.exp(-sigma * tau) * (np.cos(omega_d * tau) + sigma / omega_d * np.sin(omega_d * tau))


def last_crossing(f, band, t_max, step=1e-5):
    """Largest τ with |f(τ)| = band (bracketed on a fine grid, then Brent's method)."""
    tau = np.arange(0.0, t_max, step)
    above = np.abs(f(tau)) > band
    k = int(np.flatnonzero(above)[-1])
    return brentq(lambda s: abs(f(s)) - band, tau[k], tau[k + 1], xtol=1e-12)


def arrival(rate, amplitude=1e-3, frequency=10.0, zeta=0.15, t_signal=0.1, duration=2.0, lateral=0.0):
    """Samples of an arrival: a linear approach at 20 mm/s, then from t_signal the step response."""
    t = np.arange(0.0, duration, 1.0 / rate)
    along = np.where(
        t < t_signal, -amplitude - 0.02 * (t_signal - t), step_response(np.maximum(t - t_signal, 0), amplitude,
                                                                         frequency, zeta)
    )
    side = np.cross(U, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    positions = TARGET + along[:, None] * U + (lateral * np.sin(7.0 * t))[:, None] * side
    return t, positions


@pytest.mark.parametrize("rate", [1000.0, 200.0])
def test_damped_oscillation_overshoot_and_stabilisation_time(rate):
    amplitude, frequency, zeta, band, t_signal = 1e-3, 10.0, 0.15, 20e-6, 0.1
    t, positions = arrival(rate, amplitude, frequency, zeta, t_signal)
    r = pose_stabilisation(t, positions, t_signal, band, attained=TARGET)
    expected_overshoot = amplitude * np.exp(-zeta * np.pi / np.sqrt(1 - zeta**2))
    expected_time = last_crossing(lambda s: step_response(s, amplitude, frequency, zeta), band, 1.9)
    assert r.overshoot == pytest.approx(expected_overshoot, rel=2e-3)
    assert abs(r.stabilisation_time - expected_time) < 1.0 / rate  # within one sample period
    assert abs(r.stabilisation_time - expected_time) < 0.25 / rate  # the interpolation does better
    assert r.overshoot_time - t_signal == pytest.approx(1 / (2 * frequency * np.sqrt(1 - zeta**2)), abs=0.5 / rate)
    assert r.settled_time == pytest.approx(t_signal + r.stabilisation_time)
    np.testing.assert_allclose(r.approach, U, atol=1e-12)
    assert r.distance.shape == t.shape


def test_attained_position_and_approach_are_found_from_the_record():
    t, positions = arrival(500.0, duration=3.0, lateral=0.0)
    given = pose_stabilisation(t, positions, 0.1, 20e-6, attained=TARGET)
    found = pose_stabilisation(t, positions, 0.1, 20e-6)
    np.testing.assert_allclose(found.attained, TARGET, atol=1e-9)
    assert found.stabilisation_time == pytest.approx(given.stabilisation_time, abs=1e-6)
    assert found.overshoot == pytest.approx(given.overshoot, abs=1e-9)


def test_lateral_motion_is_not_overshoot():
    """Overshoot is measured along the approach: a sideways wobble of 50 µm adds nothing."""
    t, positions = arrival(1000.0, lateral=0.0)
    _, wobbling = arrival(1000.0, lateral=50e-6)
    plain = pose_stabilisation(t, positions, 0.1, 20e-6, attained=TARGET, approach=U)
    wobbly = pose_stabilisation(t, wobbling, 0.1, 100e-6, attained=TARGET, approach=U)
    assert wobbly.overshoot == pytest.approx(plain.overshoot, rel=1e-6)


def test_overdamped_arrival_has_no_overshoot():
    amplitude, band = 1e-3, 20e-6
    t, positions = arrival(1000.0, amplitude, 8.0, zeta=1.0 - 1e-9, duration=1.5)  # critically damped
    r = pose_stabilisation(t, positions, 0.1, band, attained=TARGET)
    assert r.overshoot == 0.0 and np.isnan(r.overshoot_time)
    expected = last_crossing(lambda s: step_response(s, amplitude, 8.0, 1.0 - 1e-9), band, 1.4)
    assert abs(r.stabilisation_time - expected) < 0.25e-3


def test_already_settled_and_never_settled():
    t = np.arange(0.0, 1.0, 1e-3)
    still = TARGET + np.zeros((len(t), 3))
    r = pose_stabilisation(t, still, 0.2003, 10e-6, attained=TARGET, approach=U)  # between two samples
    assert r.stabilisation_time == 0.0 and r.overshoot == 0.0
    ringing = TARGET + (30e-6 * np.sin(2 * np.pi * 12 * t))[:, None] * U
    r = pose_stabilisation(t, ringing, 0.2, 10e-6, attained=TARGET, approach=U)
    assert np.isnan(r.stabilisation_time) and np.isnan(r.settled_time)
    assert r.overshoot == pytest.approx(30e-6, rel=1e-4)


def test_overshoot_window_from_the_signal_or_from_the_band_entry():
    """A late signal (after the first swing beyond) sees only the second peak; the band-entry window both."""
    amplitude, frequency, zeta = 1e-3, 10.0, 0.1
    omega_d = 2 * np.pi * frequency * np.sqrt(1 - zeta**2)
    sigma = zeta * 2 * np.pi * frequency
    t = np.arange(0.0, 2.0, 1e-3)
    along = step_response(t, amplitude, frequency, zeta)
    positions = TARGET + along[:, None] * U
    late = 2.0 * np.pi / omega_d  # at the trough after the first overshoot
    by_signal = pose_stabilisation(t, positions, late, 20e-6, attained=TARGET, approach=U)
    by_entry = pose_stabilisation(t, positions, late, 20e-6, attained=TARGET, approach=U, overshoot_from="band_entry")
    assert by_signal.overshoot == pytest.approx(amplitude * np.exp(-3 * sigma * np.pi / omega_d), rel=2e-3)
    assert by_entry.overshoot == pytest.approx(amplitude * np.exp(-sigma * np.pi / omega_d), rel=2e-3)
    assert by_entry.band_entry_time < late


def test_noise_well_inside_the_band_does_not_move_the_stabilisation_time_by_more_than_a_frame():
    rate = 500.0
    t, positions = arrival(rate)
    noisy = positions + np.random.default_rng(0).normal(0.0, 1e-6, positions.shape)
    clean = pose_stabilisation(t, positions, 0.1, 20e-6, attained=TARGET)
    r = pose_stabilisation(t, noisy, 0.1, 20e-6, attained=TARGET)
    assert abs(r.stabilisation_time - clean.stabilisation_time) < 1.0 / rate
    assert r.overshoot == pytest.approx(clean.overshoot, abs=3e-6)


def test_stabilisation_rejects_bad_input():
    t, positions = arrival(200.0)
    with pytest.raises(ISO9283Error, match="t_signal"):
        pose_stabilisation(t, positions, 5.0, 1e-5)
    with pytest.raises(ISO9283Error, match="band"):
        pose_stabilisation(t, positions, 0.1, 0.0)
    with pytest.raises(ISO9283Error, match="positions"):
        pose_stabilisation(t, positions[:, :2], 0.1, 1e-5)
    with pytest.raises(ISO9283Error, match="increase"):
        pose_stabilisation(t[::-1], positions, 0.1, 1e-5)
    with pytest.raises(ISO9283Error, match="approach"):
        pose_stabilisation(t, np.tile(TARGET, (len(t), 1)), 0.1, 1e-5)
    with pytest.raises(ISO9283Error, match="overshoot_from"):
        pose_stabilisation(t, positions, 0.1, 1e-5, overshoot_from="peak")


def move(rate, distance=0.1, acceleration=2.0, speed=0.5, residual=200e-6, frequency=12.0, zeta=0.1,
         rest=0.05, tail=1.5):
    """Rest, a trapezoidal move along U, then a residual oscillation B·e^{−στ}·sin(ω_d τ) about the end."""
    t_acc = speed / acceleration
    d_acc = 0.5 * acceleration * t_acc**2
    t_const = (distance - 2 * d_acc) / speed
    t_end = rest + 2 * t_acc + t_const
    t = np.arange(0.0, t_end + tail, 1.0 / rate)
    tau = t - rest
    s = np.select(
        [tau < 0, tau < t_acc, tau < t_acc + t_const, tau < 2 * t_acc + t_const],
        [
            0.0 * tau,
            0.5 * acceleration * tau**2,
            d_acc + speed * (tau - t_acc),
            distance - 0.5 * acceleration * (2 * t_acc + t_const - tau) ** 2,
        ],
        distance,
    )
    omega = 2 * np.pi * frequency
    sigma, omega_d = zeta * omega, omega * np.sqrt(1 - zeta**2)

    def ring(x):
        return residual * np.exp(-sigma * x) * np.sin(omega_d * x)

    after = t - t_end
    s = s + np.where(after > 0, ring(np.maximum(after, 0)), 0.0)
    start = np.array([0.2, 0.1, 0.3])
    return t, start + s[:, None] * U, start, t_end, ring


def test_positioning_time_of_a_move_with_a_residual_oscillation():
    band, rate = 30e-6, 1000.0
    t, positions, start, t_end, ring = move(rate)
    r = positioning_time(t, positions, band, start=start, attained=start + 0.1 * U)
    departure = 0.05 + np.sqrt(2 * band / 2.0)
    settled = t_end + last_crossing(ring, band, 1.4)
    assert r.departure_time == pytest.approx(departure, abs=0.1 / rate)
    assert r.settled_time == pytest.approx(settled, abs=0.25 / rate)
    assert r.positioning_time == pytest.approx(settled - departure, abs=0.3 / rate)
    assert r.distance == pytest.approx(0.1, abs=1e-12)


def test_minimum_positioning_time_over_settings():
    band = 30e-6
    fast = [move(1000.0, acceleration=4.0, speed=1.0, residual=400e-6)[:2] for _ in range(3)]
    slow = [move(1000.0, acceleration=1.0, speed=0.25, residual=50e-6)[:2] for _ in range(3)]
    result = minimum_positioning_time({"100 %": fast, "25 %": slow}, band)
    times = {label: positioning_time(*records[0], band).positioning_time
             for label, records in (("100 %", fast), ("25 %", slow))}
    assert result.setting == min(times, key=times.get)
    assert result.minimum == pytest.approx(min(times.values()))
    assert set(result.per_setting) == {"100 %", "25 %"} and len(result.cycles["25 %"]) == 3


def test_path_accuracy_and_repeatability_of_a_shifted_line():
    start, end = np.array([0.3, -0.2, 0.4]), np.array([0.6, 0.1, 0.55])
    tangent = (end - start) / np.linalg.norm(end - start)
    across = np.cross(tangent, [0.0, 0.0, 1.0])
    across /= np.linalg.norm(across)
    up = np.cross(tangent, across)
    offset = 35e-6 * across + 12e-6 * up  # the systematic path error, perpendicular to the path
    cycle_offsets = np.random.default_rng(3).normal(0.0, 8e-6, (10, 2))
    commanded_angles = np.array([0.01, -0.02, 3.1])
    angle_offsets = np.array([2e-5, -1e-5, 4e-5])
    cycle_angles = np.random.default_rng(4).normal(0.0, 5e-6, (10, 3))
    s = np.linspace(-0.05, 1.05, 2000)[:, None]
    paths = []
    for j in range(10):
        shift = offset + cycle_offsets[j, 0] * across + cycle_offsets[j, 1] * up + 3e-3 * tangent  # + lag along
        angles = np.tile(commanded_angles + angle_offsets + cycle_angles[j], (len(s), 1))
        angles[:, 2] = np.mod(angles[:, 2] + np.pi, 2 * np.pi) - np.pi  # c near ±π: wrapped in the data
        paths.append(np.column_stack([start + s * (end - start) + shift, angles]))
    command = linear_path(start, end, 30, orientation=commanded_angles)
    r = path_characteristics(command, paths)
    shifts = offset[None] + cycle_offsets[:, :1] * across + cycle_offsets[:, 1:] * up
    barycentre_offset = shifts.mean(axis=0)
    distances = np.linalg.norm(shifts - barycentre_offset, axis=1)
    assert r.at_p == pytest.approx(np.linalg.norm(barycentre_offset), abs=1e-12)
    assert r.rt_p == pytest.approx(distances.mean() + 3 * distances.std(ddof=1), abs=1e-12)
    np.testing.assert_allclose(r.deviation, np.linalg.norm(barycentre_offset), atol=1e-12)
    expected_at = np.abs(angle_offsets + cycle_angles.mean(axis=0))
    np.testing.assert_allclose([r.at_a, r.at_b, r.at_c], expected_at, atol=1e-12)
    np.testing.assert_allclose([r.rt_a, r.rt_b, r.rt_c], 3 * cycle_angles.std(axis=0, ddof=1), atol=1e-12)
    assert (r.n, r.m) == (10, 30) and r.cuts.shape == (10, 30, 6)


def test_path_accuracy_of_a_circle_of_the_wrong_radius():
    center, radius, error = np.array([0.5, 0.0, 0.4]), 0.1, 42e-6
    normal = np.array([1.0, 1.0, 1.0]) / np.sqrt(3)
    e1 = np.cross(normal, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    phi = np.linspace(0.0, 2 * np.pi, 20001)
    paths = []
    for j in range(3):
        r_j = radius + error + (j - 1) * 5e-6
        paths.append(center + r_j * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2))
    command = circular_path(center, radius, normal, e1, 36)
    r = path_characteristics(command, paths)
    assert r.at_p == pytest.approx(error, abs=0.05e-6)  # polyline chords: < 0.01 µm
    spread = np.array([5e-6, 0.0, 5e-6])
    assert r.rt_p == pytest.approx(spread.mean() + 3 * spread.std(ddof=1), abs=0.05e-6)
    assert np.isnan(r.at_a) and np.isnan(r.rt_a)


def test_path_errors_name_the_path_and_point():
    command = linear_path([0, 0, 0], [0.1, 0, 0], 5)
    short = np.column_stack([np.linspace(0.0, 0.05, 50), np.zeros(50), np.zeros(50)])
    full = np.column_stack([np.linspace(-0.01, 0.11, 50), np.zeros(50), np.zeros(50)])
    with pytest.raises(ISO9283Error, match=r"paths\[1\]: never crosses .* point [234]"):
        path_characteristics(command, [full, short])
    with pytest.raises(ISO9283Error, match="at least 2 cycles"):
        path_characteristics(command, [full])
    with pytest.raises(ISO9283Error, match="max_distance"):
        path_characteristics(command, [full, full + [0, 1e-3, 0]], max_distance=0.5e-3)
    with pytest.raises(ISO9283Error, match="CommandPath"):
        CommandPath(np.zeros((3, 3)), np.zeros((3, 3)))


@pytest.mark.parametrize("turn_deg", [90.0, 60.0, 135.0])
def test_rounded_corner_deviation(turn_deg):
    """Incoming along +x to the corner at the origin, turning by φ; an arc of radius r rounds it,
    then a decaying bump A·e^{−k s}·sin(ω s) beyond the second segment's line (s along it)."""
    phi, r, bump, k, w = np.radians(turn_deg), 2e-3, 40e-6, 300.0, 900.0
    d1, d2 = np.array([1.0, 0.0, 0.0]), np.array([np.cos(phi), np.sin(phi), 0.0])
    normal_in = np.array([-np.sin(phi), np.cos(phi), 0.0])  # perpendicular to d2, toward the inside
    tangent_distance = r * np.tan(phi / 2)  # corner to each tangent point
    center = -tangent_distance * d1 + r * np.array([0.0, 1.0, 0.0])
    first = np.linspace(-0.05, -tangent_distance, 2000)[:, None] * d1
    angles = np.linspace(-np.pi / 2, -np.pi / 2 + phi, 4000)
    arc = center + r * np.column_stack([np.cos(angles), np.sin(angles), 0 * angles])
    s = np.linspace(0.0, 0.05, 20000)
    second = (tangent_distance + s)[:, None] * d2 - (bump * np.exp(-k * s) * np.sin(w * s))[:, None] * normal_in
    path = np.vstack([first, arc[1:], second[1:]])
    result = corner_deviation([0, 0, 0], d1, d2, [path, path])
    assert result.cr == pytest.approx(r / np.cos(phi / 2) - r, rel=1e-6)
    s_peak = np.arctan(w / k) / w
    assert result.co == pytest.approx(bump * np.exp(-k * s_peak) * np.sin(w * s_peak), rel=1e-4)
    smooth = np.vstack([first, arc[1:], (tangent_distance + s)[:, None] * d2])
    assert corner_deviation([0, 0, 0], d1, d2, [smooth]).co == pytest.approx(0.0, abs=1e-12)


def test_path_velocity_accuracy_repeatability_and_fluctuation():
    v_c, delta, f, rate = 0.25, 2e-3, 5.0, 1000.0
    epsilon = np.array([0.010, 0.012, 0.008, 0.011, 0.009, 0.010, 0.013, 0.007, 0.010, 0.010])
    direction = np.array([0.6, 0.0, 0.8])
    t = np.arange(0.0, 1.0 + 1.5 / rate, 1.0 / rate)  # whole periods of the fluctuation between the ends
    cycles = []
    for e in epsilon:
        s = v_c * (1 + e) * t - delta / (2 * np.pi * f) * np.cos(2 * np.pi * f * t)
        cycles.append((t, np.array([0.1, 0.2, 0.3]) + s[:, None] * direction))
    r = path_velocity(cycles, v_c)
    means = v_c * (1 + epsilon)
    assert r.av == pytest.approx((means.mean() - v_c) / v_c, abs=2e-6)
    assert r.rv == pytest.approx(3 * means.std(ddof=1) / v_c, rel=1e-3)
    # central differences of a sinusoid scale it by sinc(ωΔt); the samples hit its peaks
    omega_dt = 2 * np.pi * f / rate
    assert r.fv == pytest.approx(2 * delta * np.sin(omega_dt) / omega_dt, rel=1e-9)
    times, speeds = path_speed(t, cycles[0][1], window=0.1)  # a chord of half a period of 5 Hz… averages it
    assert speeds.max() - speeds.min() < 2 * delta * 0.7
    with pytest.raises(ISO9283Error, match="commanded_speed"):
        path_velocity(cycles, 0.0)
