"""The station runtime builds each device with the drivers' factories from the station's typed
settings, and hands each device what belongs to the station, not to the device entry."""

import socket

import numpy as np
import pytest

import drivers.camera
import drivers.robot
from drivers import DeviceConnectionError
from drivers.camera import PylonSettings
from drivers.robot import URRtdeSettings
from procedures.station import StationFile, StationRuntime
from tests.fakes import FakeCamera, FakeCell, FakeRobot, station_dict


def test_robot_gets_its_settings_the_station_envelope_and_the_opr_as_tcp(monkeypatch):
    station = StationFile.model_validate(station_dict())
    made = {}

    def create(settings, *, name, envelope):
        made.update(settings=settings, name=name, envelope=envelope, robot=FakeRobot(FakeCell()))
        return made["robot"]

    monkeypatch.setattr(drivers.robot, "create", create)
    runtime = StationRuntime(station)
    robot = runtime.robot
    assert robot is made["robot"] and made["name"] == "robot"
    assert isinstance(made["settings"], URRtdeSettings) and made["settings"].host == "127.0.0.1"
    # The envelope is the station's, so the driver refuses exactly what the station refuses.
    assert made["envelope"] is runtime.envelope
    np.testing.assert_array_equal(runtime.envelope.box_max, station.envelope.box_max)
    # Commanded poses are OPR poses: the TCP is the nominal OPR mounting, set on open.
    np.testing.assert_array_equal(robot.tcp_offset(), station.frames.tcp_offset)
    assert runtime.robot is robot and runtime.device("robot") is robot and runtime.opened("robot") is robot
    runtime.close()
    assert runtime.opened("robot") is None


def test_each_camera_is_built_from_its_own_entry(monkeypatch):
    station = StationFile.model_validate(station_dict())
    cell = FakeCell()
    made = {}

    def create(settings, *, name):
        made[name] = settings
        return FakeCamera(cell, name.split(":")[1])

    monkeypatch.setattr(drivers.camera, "create", create)
    runtime = StationRuntime(station)
    assert {runtime.camera(s).screen for s in "xyz"} == {"x", "y", "z"}
    assert runtime.device("camera:y") is runtime.camera("y")
    assert {name: settings.serial for name, settings in made.items()} == {
        "camera:x": "fake-x", "camera:y": "fake-y", "camera:z": "fake-z"}
    assert all(isinstance(settings, PylonSettings) for settings in made.values())
    runtime.close()


def test_given_devices_get_the_tcp_too():
    station = StationFile.model_validate(station_dict())
    robot = FakeRobot(FakeCell())
    runtime = StationRuntime(station, devices={"robot": robot})
    assert runtime.robot is robot
    np.testing.assert_array_equal(robot.tcp_offset(), [0, 0, 0.08, 0, 0, 0])
    runtime.close()


def test_a_device_the_station_lacks_is_a_typed_error():
    station = StationFile.model_validate(station_dict(devices={**station_dict()["devices"], "rotary_table": None}))
    runtime = StationRuntime(station)
    with pytest.raises(DeviceConnectionError, match="the station file configures no rotary_table"):
        runtime.device("rotary_table")
    with pytest.raises(DeviceConnectionError, match="no such device role"):
        runtime.device("camera:w")


def test_an_unreachable_device_is_a_connection_error_naming_the_role():
    """The real factory: a Modbus table at a loopback port where nothing listens."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        free_port = probe.getsockname()[1]
    devices = {**station_dict()["devices"], "rotary_table": {"adapter": "modbus_tcp", "host": "127.0.0.1",
                                                             "port": free_port, "timeout": 0.2, "retries": 0}}
    runtime = StationRuntime(StationFile.model_validate(station_dict(devices=devices)))
    with pytest.raises(DeviceConnectionError, match="cannot be reached") as caught:
        runtime.device("rotary_table")
    assert caught.value.device == "rotary_table"
    assert runtime.opened("rotary_table") is None
    runtime.close()
