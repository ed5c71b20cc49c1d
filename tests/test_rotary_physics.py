"""Table physics on a fake clock: power-on state, soft limits, trapezoid timing, encoder errors within
bound, backlash, homing, alarms."""

import math

import numpy as np
import pytest

from sim_devices import World
from sim_devices.rotary_table import ARCSEC, CommandRefused, RotaryTableTwin, TableConfig, TablePhysics, ValueRefused


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


@pytest.fixture
def clock():
    return FakeClock()


def _ready(table: TablePhysics, clock: FakeClock) -> TablePhysics:
    """Servo on and the reference move done, as a set-up does after power-on."""
    table.enable(True)
    table.home()
    clock.t += 30
    assert table.status()["homed"] and table.status()["in_position"]
    return table


def test_power_on_is_servo_off_and_unreferenced(clock):
    table = TablePhysics(TableConfig(), clock=clock, initial_angle=0.3)
    status = table.status()
    assert not status["enabled"] and not status["homed"] and not status["moving"]
    with pytest.raises(CommandRefused) as refused:
        table.move_to_counts(1000)
    assert refused.value.reason == "servo_off"
    with pytest.raises(CommandRefused, match="servo off"):
        table.home()  # the reference move needs the servo too
    table.enable(True)
    with pytest.raises(CommandRefused) as refused:
        table.move_to_counts(1000)
    assert refused.value.reason == "unreferenced"
    assert table.true_angle() == pytest.approx(0.3) and not table.status()["moving"]  # nothing moved
    _ready(table, clock)
    table.move_to_counts(1000)
    assert table.status()["moving"]


def test_without_requires_homing_an_unreferenced_table_moves(clock):
    table = TablePhysics(TableConfig(requires_homing=False), clock=clock)
    table.enable(True)
    table.move_to_counts(1000)
    assert table.status()["moving"] and not table.status()["homed"]


def test_soft_limits_refuse_the_target_before_anything_moves(clock):
    config = TableConfig(travel_min=-1.0, travel_max=2.0)
    table = _ready(TablePhysics(config, clock=clock), clock)
    beyond = int(2.0 / table.quantum) + 1
    for move in (lambda: table.move_to_counts(beyond), lambda: table.move_to_counts(-beyond),
                 lambda: table.move_by_counts(beyond)):
        with pytest.raises(ValueRefused) as refused:
            move()
        assert refused.value.reason == "travel" and "soft limits" in str(refused.value)
        status = table.status()
        assert not status["moving"] and status["target_counts"] == 0 and status["in_position"]
    table.move_to_counts(int(2.0 / table.quantum))  # up to the limit is inside
    clock.t += 30
    with pytest.raises(ValueRefused):
        table.move_by_counts(10)  # relative moves count from the target
    assert TableConfig().travel_max == pytest.approx(math.radians(36_000))  # ±100 turns by default
    with pytest.raises(ValueError, match="travel_min"):
        TableConfig(travel_min=1.0, travel_max=1.0)


def test_default_model_reports_within_half_an_arcsecond():
    assert TableConfig().reported_error_bound() < 0.5 * ARCSEC


def test_trapezoid_takes_the_analytic_time(clock):
    config = TableConfig(max_speed=0.5, inertia=0.05, peak_torque=0.1, seed=1)  # a = 2 rad/s²
    table = _ready(TablePhysics(config, clock=clock), clock)
    distance = 1.0
    table.move_to_counts(round(distance / table.quantum))
    expected = distance / 0.5 + 0.5 / 2.0  # cruise + one ramp's worth (trapezoid with ramps of 0.25 s)
    clock.t += expected - 0.01
    assert table.status()["moving"]
    clock.t += 0.02
    assert not table.status()["moving"]
    assert not table.status()["in_position"]  # still settling
    clock.t += config.settle_time
    assert table.status()["in_position"]
    assert abs(table.true_angle() - distance) < config.reported_error_bound() + table.quantum


def test_reported_true_and_commanded_differ_by_realistic_amounts(clock):
    config = TableConfig(seed=4)
    table = _ready(TablePhysics(config, clock=clock, initial_angle=0.4), clock)
    bound = config.reported_error_bound()
    errors = []
    for target in np.linspace(-3.0, 3.0, 25):
        counts = round(target / table.quantum)
        table.move_to_counts(counts)
        clock.t += 20.0
        reported = table.read_counts() * table.quantum
        true = table.true_angle()
        assert abs(reported - true) <= bound + 1e-12
        assert abs(reported - counts * table.quantum) <= table.quantum + 3 * config.noise_std
        errors.append(true - counts * table.quantum)
    # the periodic error and the backlash really show: true ≠ commanded by a good part of the bound
    assert np.ptp(errors) > config.periodic_error


def test_backlash_depends_on_approach_direction(clock):
    config = TableConfig(periodic_error=0.0, noise_std=0.0, backlash=2 * ARCSEC)
    table = _ready(TablePhysics(config, clock=clock), clock)
    target = round(0.5 / table.quantum)
    table.move_to_counts(target + 1000)
    clock.t += 10
    table.move_to_counts(target)  # approach from above
    clock.t += 10
    from_above = table.true_angle()
    table.move_to_counts(target - 1000)
    clock.t += 10
    table.move_to_counts(target)  # approach from below
    clock.t += 10
    from_below = table.true_angle()
    assert from_above - from_below == pytest.approx(config.backlash, abs=1e-12)


def test_homing_defines_zero_and_stop_decelerates(clock):
    config = TableConfig(seed=2)
    table = TablePhysics(config, clock=clock, initial_angle=0.7)
    assert table.read_counts() in range(-1, 2)  # counter starts at zero wherever the table is
    table.enable(True)
    table.home()
    clock.t += 30
    status = table.status()
    assert status["homed"] and status["in_position"]
    assert abs(table.true_angle()) < 1e-12  # the reference mark is the true zero
    assert abs(table.read_counts() * table.quantum) <= config.reported_error_bound()
    table.move_to_counts(round(2.0 / table.quantum))
    clock.t += 1.0
    speed = abs(table.status()["velocity"])
    table.stop()
    stop_time = speed / config.acceleration
    clock.t += stop_time + config.settle_time + 1e-6
    assert table.status()["in_position"]
    rest = table.true_angle()
    clock.t += 5
    assert table.true_angle() == rest


def test_alarm_refuses_moves_until_reset(clock):
    table = _ready(TablePhysics(TableConfig(), clock=clock), clock)
    table.raise_alarm("following_error")
    with pytest.raises(CommandRefused, match="alarm") as refused:
        table.move_to_counts(1000)
    assert refused.value.reason == "alarm"
    table.alarm_reset()
    table.move_to_counts(1000)
    with pytest.raises(ValueRefused):
        table.set_speed(10 * table.config.max_speed)


def test_world_follows_the_table_only_when_the_opr_is_on_it(clock):
    world = World()
    twin = RotaryTableTwin(world, {"transports": [], "table": {"seed": 1, "requires_homing": False}}, clock=clock)
    twin.physics.enable(True)
    twin.physics.move_to_counts(round(1.0 / twin.physics.quantum))
    clock.t += 20
    twin.sync()
    assert world.table_angle() == 0.0 and world.mount == "robot"
    world.mount_on_table("z")
    twin.sync()
    assert world.table_angle() == twin.physics.true_angle()
    assert world.state().settled
    assert abs(world.table_angle() - 1.0) < 1 * ARCSEC
    twin.physics.move_to_counts(round(2.0 / twin.physics.quantum))
    clock.t += 0.5
    twin.sync()
    assert not world.state().settled
    clock.t += 20
    twin.sync()
    assert world.state().settled and abs(world.table_angle() - 2.0) < 1 * ARCSEC
    assert math.isclose(world.truth.entries("pose")[-1]["table_angle"], world.table_angle())
