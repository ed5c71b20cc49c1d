"""The station runtime hands each device what belongs to the station, not to the device entry."""

import numpy as np

import drivers.robot
from procedures._models import StationFile
from procedures._station import StationRuntime
from tests.fakes import FakeCell, FakeRobot, station_dict


def test_robot_gets_the_station_envelope_and_the_opr_as_tcp(monkeypatch):
    station = StationFile.model_validate(station_dict())
    made = {}

    def create(config, *, name):
        made["config"], made["name"] = dict(config), name
        made["robot"] = FakeRobot(FakeCell())
        return made["robot"]

    monkeypatch.setattr(drivers.robot, "create", create)
    runtime = StationRuntime(station)
    robot = runtime.robot
    assert robot is made["robot"] and made["name"] == "robot"
    # The envelope is the station's, so the driver refuses exactly what the station refuses.
    assert made["config"]["envelope"] == station.envelope.model_dump()
    assert made["config"]["adapter"] == station.devices.robot.adapter
    # Commanded poses are OPR poses: the TCP is the nominal OPR mounting, set on open.
    np.testing.assert_array_equal(robot.tcp_offset(), station.frames.tcp_offset)
    assert robot.connected
    runtime.close()


def test_given_devices_get_the_tcp_too():
    station = StationFile.model_validate(station_dict())
    robot = FakeRobot(FakeCell())
    runtime = StationRuntime(station, devices={"robot": robot})
    assert runtime.robot is robot
    np.testing.assert_array_equal(robot.tcp_offset(), [0, 0, 0.08, 0, 0, 0])
    runtime.close()
