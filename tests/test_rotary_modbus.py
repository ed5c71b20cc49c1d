"""The table twin's Modbus faces driven by the real pymodbus clients, TCP and RTU: exception codes,
other device ids, broadcast, read-back values writable; and what the driver makes of them."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator

import pytest
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ModbusIOException

from drivers import DeviceTimeout
from drivers.rotary_table import CommandRefused, TableFault, create
from sim_devices import World
from sim_devices.rotary_table import RotaryTableTwin

pytestmark = pytest.mark.timeout(120)

FAST_TABLE = {"max_speed": 3.0, "peak_torque": 1.0, "home_speed": 3.0, "seed": 3}
UNIT = 5  # not the default, so a client that ignores the unit id is caught
# The documented default map (docs/rotary_table.md).
STATUS, POSITION_COMMAND, VELOCITY, ACCELERATION, CONTROL = 1, 4, 6, 7, 124
ENABLED, HOMED = 0, 13
ENABLE, HOME, MOVE_ABSOLUTE = 0x9F, 0x6E, 0x67
ANSWER_TIMEOUT = 0.3


@pytest.fixture(scope="module")
def twin() -> Iterator[tuple[World, RotaryTableTwin, dict]]:
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # it logs every unanswered request
    world = World()
    twin = RotaryTableTwin(world, {"transports": ["modbus_tcp", "modbus_rtu"], "unit": UNIT, "table": FAST_TABLE})
    endpoints = twin.start()
    yield world, twin, endpoints
    twin.stop()
    world.truth.close()


@pytest.fixture
def tcp(twin) -> Iterator[ModbusTcpClient]:
    client = ModbusTcpClient("127.0.0.1", port=twin[2]["modbus_tcp_port"], timeout=ANSWER_TIMEOUT, retries=0)
    assert client.connect()
    yield client
    client.close()


@pytest.fixture
def rtu(twin) -> Iterator[ModbusSerialClient]:
    client = ModbusSerialClient(twin[2]["modbus_rtu_port"], baudrate=115200, timeout=ANSWER_TIMEOUT, retries=0)
    assert client.connect()
    yield client
    client.close()


@pytest.fixture(params=["tcp", "rtu"])
def client(request, tcp, rtu):
    return tcp if request.param == "tcp" else rtu


def _status(client) -> int:
    reply = client.read_holding_registers(STATUS, count=1, device_id=UNIT)
    assert not reply.isError(), reply
    return int(reply.registers[0])


def _nothing_arrives(client, seconds: float = 0.2) -> bool:
    """No byte reaches the client's serial port within ``seconds`` (not even a late reply)."""
    time.sleep(seconds)
    return client.socket.in_waiting == 0


def test_rtu_is_silent_for_other_device_ids(rtu):
    for unit in (1, 6, 247):
        started = time.monotonic()
        with pytest.raises(ModbusIOException):
            rtu.read_holding_registers(STATUS, count=1, device_id=unit)
        assert time.monotonic() - started >= ANSWER_TIMEOUT * 0.9  # waited out: nobody answered
        assert _nothing_arrives(rtu)
    assert _status(rtu) >= 0  # and the drive still answers its own id


def test_tcp_answers_its_own_id_zero_and_255_and_exception_11_for_others(tcp):
    expected = _status(tcp)
    for unit in (0, 255):
        reply = tcp.read_holding_registers(STATUS, count=1, device_id=unit)
        assert not reply.isError() and reply.registers == [expected] and reply.dev_id == unit
    for unit in (1, 6, 247):
        reply = tcp.read_holding_registers(STATUS, count=1, device_id=unit)
        assert reply.isError() and reply.exception_code == 11, (unit, reply)


def test_rtu_broadcast_writes_are_executed_without_a_reply(twin, rtu):
    _, table, _ = twin
    table.physics.enable(False)
    assert not _status(rtu) >> ENABLED & 1
    assert rtu.write_register(CONTROL, ENABLE, device_id=0, no_response_expected=True) is None
    assert _nothing_arrives(rtu)
    assert _status(rtu) >> ENABLED & 1  # executed
    assert rtu.write_register(VELOCITY, 48, device_id=0, no_response_expected=True) is None
    assert _nothing_arrives(rtu)
    assert rtu.read_holding_registers(VELOCITY, count=1, device_id=UNIT).registers == [48]


def test_exception_codes(twin, client):
    _, table, _ = twin
    table.physics.enable(False)
    refused = client.write_register(CONTROL, HOME, device_id=UNIT)  # cannot act now: servo off
    assert refused.isError() and refused.exception_code == 4
    assert not client.write_register(CONTROL, ENABLE, device_id=UNIT).isError()
    if not _status(client) >> HOMED & 1:
        refused = client.write_register(CONTROL, MOVE_ABSOLUTE, device_id=UNIT)  # unreferenced
        assert refused.isError() and refused.exception_code == 4
        assert not client.write_register(CONTROL, HOME, device_id=UNIT).isError()
        deadline = time.monotonic() + 10
        while not _status(client) >> HOMED & 1:
            assert time.monotonic() < deadline
            time.sleep(0.02)
    for word in (0, 0xFFFF):  # a speed of zero, one far above the maximum
        refused = client.write_register(VELOCITY, word, device_id=UNIT)
        assert refused.isError() and refused.exception_code == 3, word
    beyond = 101 * 2**24  # 101 turns: beyond the ±100-turn soft limits
    assert not client.write_registers(POSITION_COMMAND, [beyond >> 16, beyond & 0xFFFF], device_id=UNIT).isError()
    refused = client.write_register(CONTROL, MOVE_ABSOLUTE, device_id=UNIT)
    assert refused.isError() and refused.exception_code == 3
    assert not table.truth()["moving"] and not table.truth()["alarms"]
    refused = client.write_register(STATUS, 0, device_id=UNIT)  # read-only register
    assert refused.isError() and refused.exception_code == 2


def test_every_writable_value_read_back_can_be_written_back(twin, client):
    # (The control register is left out: writing its opcode back runs that command again.)
    for address in (POSITION_COMMAND, POSITION_COMMAND + 1, VELOCITY, ACCELERATION):
        value = client.read_holding_registers(address, count=1, device_id=UNIT).registers[0]
        reply = client.write_register(address, value, device_id=UNIT)
        assert not reply.isError(), (address, value, reply)
        assert client.read_holding_registers(address, count=1, device_id=UNIT).registers == [value]
    settings = client.read_holding_registers(VELOCITY, count=2, device_id=UNIT).registers
    assert not client.write_registers(VELOCITY, settings, device_id=UNIT).isError()


def test_the_driver_on_the_wrong_unit_fails_in_bounded_time(twin):
    endpoints = twin[2]
    cases = [({"adapter": "modbus_rtu", "port": endpoints["modbus_rtu_port"]}, "no answer"),
             ({"adapter": "modbus_tcp", "host": "127.0.0.1", "port": endpoints["modbus_tcp_port"]}, "code 11")]
    for config, cause in cases:
        started = time.monotonic()
        with pytest.raises(DeviceTimeout, match=cause) as failed:
            create({**config, "unit": UNIT + 1, "timeout": 0.2, "retries": 1}, name="table").open()
        assert failed.value.device == "table" and "status register" in failed.value.operation
        assert time.monotonic() - started < 3.0


def test_the_driver_maps_3_to_a_refused_command_and_4_to_a_fault(twin):
    world, table_twin, endpoints = twin
    world.mount_on_table("x")
    config = {"adapter": "modbus_rtu", "port": endpoints["modbus_rtu_port"], "unit": UNIT}
    try:
        with create(config, name="table") as table:
            with pytest.raises(CommandRefused, match="code 3"):
                table.move_absolute(table_twin.table_config.travel_max + 0.5)
            table_twin.physics.enable(False)
            with pytest.raises(TableFault, match="code 4.*the servo is off"):
                table.move_absolute(0.1)
            table_twin.physics.enable(True)
            table_twin.raise_alarm("over_temperature")
            with pytest.raises(TableFault, match="over temperature"):
                table.home()
            table_twin.faults("modbus_rtu").arm("exception", code=4)
            with pytest.raises(TableFault, match="code 4.*over temperature"):
                table.position()
            table.reset_alarm()
            table.move_absolute(0.2)
            assert abs(table.wait_in_position(timeout=10) - world.table_angle()) < 1e-5
    finally:
        table_twin.alarm_reset()
        world.mount_on_robot()
