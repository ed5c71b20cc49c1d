"""Each rotary-table adapter against its twin over the real client library, with every fault:
open() from the power-on state, soft limits, refused values, alarms, transport faults."""

import logging
import math
import os
import socket
import threading
import time

import pytest

from drivers import DeviceConnectionError, DeviceTimeout, MotionRefused, ProtocolError, SettingsError
from drivers.rotary_table import (
    CommandRefused,
    GcsSerialSettings,
    GcsTable,
    GcsTcpSettings,
    ModbusTable,
    RegisterMap,
    RotaryTable,
    TableFault,
    create,
)
from sim_devices import World
from sim_devices.rotary_table import ARCSEC, RotaryTableTwin

TIMEOUT = 0.2
RETRIES = 2
FAST_TABLE = {"max_speed": 3.0, "peak_torque": 1.0, "home_speed": 3.0, "seed": 5}
TRANSPORTS = ["modbus_tcp", "modbus_rtu", "gcs", "gcs_tcp"]  # the twin's endpoints
# The faults whose effect outlasts the request it hit (a late reply, a muted or pulled line); every other
# fault is over once the driver has its answer (or gave up on it), so nothing is left to drain.
TIMED_FAULTS = {"delay", "slow", "stall", "disconnect"}


@pytest.fixture(scope="module")
def cell():
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # the faults make it complain loudly
    world = World()
    world.mount_on_table("z")
    twin = RotaryTableTwin(world, {"table": FAST_TABLE})
    endpoints = twin.start()
    yield world, twin, endpoints
    twin.stop()


def _config(transport, endpoints):
    if transport == "modbus_tcp":
        return {"adapter": "modbus_tcp", "host": "127.0.0.1", "port": endpoints["modbus_tcp_port"], "unit": 1}
    if transport == "modbus_rtu":
        return {"adapter": "modbus_rtu", "port": endpoints["modbus_rtu_port"], "baudrate": 115200}
    if transport == "gcs_tcp":
        return {"adapter": "gcs_tcp", "host": "127.0.0.1", "port": endpoints["gcs_tcp_port"], "axis": "1"}
    return {"adapter": "gcs_serial", "port": endpoints["gcs_port"], "axis": "1"}


@pytest.fixture(scope="module", params=TRANSPORTS)
def connected(request, cell):
    world, twin, endpoints = cell
    transport = request.param
    table = create({**_config(transport, endpoints), "timeout": TIMEOUT, "retries": RETRIES}, name="table")
    table.open()  # servo on and the reference move, once per twin (the first transport's open does them)
    truth = twin.truth()
    assert truth["enabled"] and truth["homed"] and truth["in_position"]
    yield world, twin, table, transport
    table.close()


@pytest.fixture
def rig(connected):
    world, twin, table, transport = connected
    yield connected
    if any(kind.value in TIMED_FAULTS for kind, _ in twin.faults(transport).fired()):
        time.sleep(2 * TIMEOUT)  # let a late answer (or a silence) of a fault drain before the next test
    twin.faults(transport).clear()
    twin.faults(transport)._fired.clear()
    twin.physics.alarm_reset()


def _bound(twin):
    return twin.table_config.reported_error_bound()


def test_moves_agree_with_the_worlds_truth(rig):
    world, twin, table, _ = rig
    assert isinstance(table, RotaryTable)
    for target in (0.5, -0.25, 0.25):
        table.move_absolute(target, speed=2.0)
        reported = table.wait_in_position(timeout=10)
        assert world.state().settled
        assert abs(reported - world.table_angle()) <= _bound(twin)
        assert (
            abs(reported - target)
            <= 2 * 2 * math.pi / twin.table_config.counts_per_rev + 3 * twin.table_config.noise_std
        )
    table.move_relative(0.25)
    reported = table.wait_in_position(timeout=10)
    assert abs(reported - 0.5) <= _bound(twin)
    assert abs(world.table_angle() - 0.5) <= _bound(twin)
    state = table.state()
    assert state.in_position and state.homed and not state.moving and state.fault is None


def test_stop_and_alarm(rig):
    world, twin, table, _ = rig
    table.move_absolute(3.0, speed=1.0)
    time.sleep(0.2)
    assert table.state().moving
    table.stop()
    rest = table.wait_in_position(timeout=10)
    assert 0.0 < rest < 3.0
    assert abs(rest - world.table_angle()) <= _bound(twin)
    twin.control("alarm", name="following_error")
    with pytest.raises(TableFault) as raised:
        table.move_absolute(1.0)
        table.wait_in_position(timeout=5)
    assert "following error" in str(raised.value) or "1024" in str(raised.value)
    assert table.state().fault is not None
    table.reset_alarm()
    table.move_absolute(0.25)
    assert abs(table.wait_in_position(timeout=10) - world.table_angle()) <= _bound(twin)


def test_bad_input_is_refused_before_sending(rig):
    _, _, table, _ = rig
    with pytest.raises(MotionRefused):
        table.move_absolute(float("nan"))
    with pytest.raises(MotionRefused):
        table.move_absolute(0.1, speed=-1.0)


def test_the_soft_limits_are_the_same_on_every_face(rig):
    """A target beyond the table's travel (±100 turns) is refused by the table itself, nothing moves,
    and the table stays healthy (Modbus exception 3 on the opcode write, GCS error 7)."""
    world, twin, table, _ = rig
    start = table.wait_in_position(timeout=10)
    travel = twin.table_config.travel_max
    for target in (travel + 0.01, -travel - 0.01):
        with pytest.raises(CommandRefused, match="code 3|GCS error 7") as refused:
            table.move_absolute(target)
        assert refused.value.device == "table" and "move_absolute" in refused.value.operation
        state = table.state()
        assert state.in_position and not state.moving and state.fault is None
        assert abs(world.table_angle() - start) <= _bound(twin)
    with pytest.raises(CommandRefused):
        table.move_relative(travel + 0.01 - min(start, 0.0))  # lands just beyond the upper limit
    with pytest.raises(CommandRefused, match="code 3|GCS error 17"):  # faster than the table can go
        table.move_absolute(0.1, speed=10 * twin.table_config.max_speed)
    assert not table.state().moving
    table.move_absolute(start + 0.1)  # the table still takes a good command
    assert abs(table.wait_in_position(timeout=10) - (start + 0.1)) <= 2 * _bound(twin)


TRANSPORT_FAULTS = [
    ("drop_reply", {}),
    ("delay", {"seconds": 1.5 * TIMEOUT}),  # late: after the driver gave up, before it retries
    ("garbage", {}),
    ("garbage", {"mode": "replace"}),
    ("truncate", {}),
    ("bad_crc", {}),
    ("stall", {"seconds": 1.5 * TIMEOUT}),
    ("disconnect", {"seconds": 1.5 * TIMEOUT}),
]


@pytest.mark.parametrize("kind,params", TRANSPORT_FAULTS, ids=[f"{k}-{p.get('mode', '')}" for k, p in TRANSPORT_FAULTS])
def test_a_single_fault_is_retried_and_the_value_is_right(rig, kind, params):
    world, twin, table, transport = rig
    twin.faults(transport).arm(kind, count=1, **params)
    started = time.monotonic()
    reported = table.position()
    assert time.monotonic() - started < (RETRIES + 1) * 4 * TIMEOUT + 1.0
    assert abs(reported - world.table_angle()) <= _bound(twin)
    assert twin.faults(transport).fired() and twin.faults(transport).fired()[-1][0].value == kind


@pytest.mark.parametrize("kind,error", [("drop_reply", DeviceTimeout), ("bad_crc", ProtocolError)])
def test_a_persistent_fault_is_a_typed_error_in_bounded_time(rig, kind, error):
    _, twin, table, transport = rig
    twin.faults(transport).arm(kind, count=-1)
    started = time.monotonic()
    with pytest.raises(error) as raised:
        table.position()
    # (retries + 1) × (answer timeout + guard), and for GCS the diagnostic ERR? as well
    assert time.monotonic() - started < 2 * (RETRIES + 1) * 2 * TIMEOUT + 1.5
    assert raised.value.device == "table" and raised.value.cause
    twin.faults(transport).clear()
    table.position()  # and it recovers at once (a dropped or corrupted answer leaves nothing late to drain)


def test_a_lost_command_reply_does_not_move_twice(rig):
    world, twin, table, transport = rig
    start = table.wait_in_position(timeout=10)
    twin.faults(transport).arm("drop_reply", count=1)
    table.move_relative(0.5)  # the write's (or ERR?'s) answer is lost and retried
    reported = table.wait_in_position(timeout=10)
    assert abs(reported - (start + 0.5)) <= 2 * _bound(twin)
    assert abs(world.table_angle() - reported) <= _bound(twin)


def test_exception_answers_become_typed_errors(rig):
    _, twin, table, transport = rig
    if transport.startswith("gcs"):
        twin.faults(transport).arm("exception", count=1, code=7)
        with pytest.raises(CommandRefused, match="GCS error 7"):
            table.move_absolute(0.3)
        twin.faults(transport).arm("exception", count=1, code=5)
        with pytest.raises(TableFault, match="GCS error 5"):
            table.move_absolute(0.3)
        return
    twin.faults(transport).arm("exception", count=1, code=2)
    with pytest.raises(ProtocolError, match=r"encoder position register 0x0002.*code 2"):
        table.position()
    twin.faults(transport).arm("exception", count=1, code=3)
    with pytest.raises(CommandRefused, match=r"encoder position register 0x0002.*code 3"):
        table.position()
    twin.faults(transport).arm("exception", count=1, code=4)
    with pytest.raises(TableFault, match="code 4"):
        table.position()
    twin.faults(transport).arm("exception", count=1, code=6)  # busy: retried
    assert abs(table.position() - twin.physics.true_angle()) <= _bound(twin)
    twin.faults(transport).arm("exception", count=-1, code=6)
    with pytest.raises(DeviceTimeout, match="code 6"):
        table.position()


def test_modbus_tcp_disconnect_reconnects(cell):
    _, twin, endpoints = cell
    table = create({**_config("modbus_tcp", endpoints), "timeout": TIMEOUT, "retries": RETRIES}, name="table")
    with table:
        twin.faults("modbus_tcp").arm("disconnect", count=1)
        assert abs(table.position() - twin.physics.true_angle()) <= _bound(twin)
        twin.faults("modbus_tcp").arm("disconnect", count=-1)
        with pytest.raises(DeviceConnectionError):
            table.position()
        twin.faults("modbus_tcp").clear()


def test_gcs_tcp_disconnect_reconnects(cell):
    """A PI controller's TCP connection closed under a query: the driver reconnects and asks again."""
    _, twin, endpoints = cell
    table = create({**_config("gcs_tcp", endpoints), "timeout": TIMEOUT, "retries": RETRIES}, name="table")
    with table:
        twin.faults("gcs_tcp").arm("disconnect", count=1)
        assert abs(table.position() - twin.physics.read_counts() * twin.physics.quantum) <= _bound(twin)
        assert twin.faults("gcs_tcp").fired()[-1][0].value == "disconnect"
        twin.faults("gcs_tcp").arm("disconnect", count=-1)
        with pytest.raises(DeviceConnectionError):
            table.position()
        twin.faults("gcs_tcp").clear()
        table.position()


# ------------------------------------------------------------------------------ open() from power-on
@pytest.fixture(params=TRANSPORTS)
def fresh_twin(request):
    """A twin just powered on (servo off, unreferenced) and the adapter settings for one of its faces."""
    world = World()
    world.mount_on_table("z")
    twin = RotaryTableTwin(world, {"transports": [request.param], "table": FAST_TABLE})
    endpoints = twin.start()
    yield world, twin, {**_config(request.param, endpoints), "timeout": 0.5}
    twin.stop()
    world.truth.close()


def test_open_switches_the_servo_on_and_references_the_table(fresh_twin):
    world, twin, config = fresh_twin
    truth = twin.truth()
    assert not truth["enabled"] and not truth["homed"]  # the power-on state
    with create(config, name="table") as table:
        truth = twin.truth()
        assert truth["enabled"] and truth["homed"] and truth["in_position"]
        assert abs(world.table_angle()) <= _bound(twin)  # the reference mark is the true zero
        table.move_absolute(0.3)
        assert abs(table.wait_in_position(timeout=10) - world.table_angle()) <= _bound(twin)
    with create(config, name="table") as table:  # a second open finds the table ready and leaves it
        assert abs(table.position() - 0.3) <= 2 * _bound(twin)


def test_open_without_reference_leaves_the_table_as_it_is(fresh_twin):
    _, twin, config = fresh_twin
    with create({**config, "reference_on_open": False}, name="table") as table:
        assert not twin.truth()["enabled"] and not twin.truth()["homed"]
        with pytest.raises(TableFault, match="servo is off|GCS error 5"):
            table.move_absolute(0.3)  # the table itself refuses: servo off
        assert not twin.truth()["moving"]


def test_open_with_an_alarm_present(fresh_twin):
    _, twin, config = fresh_twin
    twin.physics.enable(True)
    twin.raise_alarm("encoder_fault")
    if config["adapter"].startswith("modbus"):  # a drive alarm is the operator's to clear, not open()'s
        with pytest.raises(TableFault, match="encoder fault") as failed:
            create(config, name="table").open()
        assert failed.value.operation == "open" and not twin.truth()["homed"]
    else:  # a PI controller shows a motion error as servo off, and SVO 1 1 is how it is cleared
        with create(config, name="table"):
            assert twin.truth()["homed"] and not twin.truth()["alarms"]


def test_a_slow_camera_never_holds_up_the_tables_answers(fresh_twin):
    """A settled angle reaches the world only once every camera has rendered it (here one that takes
    1.5 s): meanwhile the drive keeps answering and says 'not in position'; in position comes only
    after the camera had the angle. The proof is answers that began and ended inside the camera's
    sleep (a drive held up by the camera could give none), not a tight answer timeout: on a starved
    host one answer can take half a second."""
    world, twin, config = fresh_twin
    sleeps: list[tuple[float, float, float]] = []  # (began, ended, angle rendered)

    def slow_camera(state):
        if state.settled:
            began = time.monotonic()
            time.sleep(1.5)
            sleeps.append((began, time.monotonic(), state.table_angle))

    answers: list[tuple[float, float, bool]] = []  # (asked, answered, in position)
    with create({**config, "timeout": 2.0, "retries": 0}, name="table") as table:
        world.subscribe(slow_camera)
        try:
            table.move_absolute(0.3)
            deadline = time.monotonic() + 30.0
            while time.monotonic() < deadline:
                asked = time.monotonic()
                state = table.state()
                answers.append((asked, time.monotonic(), state.in_position))
                if state.in_position:
                    break
                time.sleep(0.01)
        finally:
            world.unsubscribe(slow_camera)
    assert sleeps and answers[-1][2], "the table never came in position"
    began, ended, _ = sleeps[0]
    inside = [a for a in answers if began <= a[0] and a[1] <= ended]
    assert len(inside) >= 2 and not any(a[2] for a in inside)  # answered, and honestly, while the camera slept
    assert answers[-1][1] >= sleeps[-1][1]  # in position only once the camera had rendered the angle
    assert abs(sleeps[-1][2] - world.table_angle()) < 1e-12
    assert abs(state.position - world.table_angle()) <= _bound(twin)


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_open_gives_up_on_a_reference_move_that_does_not_end(transport):
    world = World()
    twin = RotaryTableTwin(world, {"transports": [transport], "table": {**FAST_TABLE, "home_speed": 0.001}})
    endpoints = twin.start()  # homing from power-on goes 0.5° below the mark and back: ~17 s at this speed
    try:
        started = time.monotonic()
        with pytest.raises(DeviceTimeout, match="not referenced after 0.3 s") as failed:
            create({**_config(transport, endpoints), "reference_timeout": 0.3}, name="table").open()
        assert failed.value.device == "table" and "open: reference move" in failed.value.operation
        assert time.monotonic() - started < 5.0
        assert twin.truth()["enabled"] and twin.truth()["homing"]  # the servo did come on
    finally:
        twin.stop()
        world.truth.close()


def test_non_default_register_map(cell):
    """Driver and twin both follow the configured map (other addresses, little-endian word order)."""
    world = World()
    world.mount_on_table("x")
    register_map = {"alarm": 40, "status": 41, "encoder_position": 10, "position_command": 20, "velocity": 30,
                    "acceleration": 31, "actual_velocity": 32, "control": 50, "word_order": "little",
                    "counts_per_rev": 8_388_608}
    twin = RotaryTableTwin(world, {"transports": ["modbus_tcp"], "table": FAST_TABLE, "register_map": register_map})
    endpoints = twin.start()
    try:
        config = {**_config("modbus_tcp", endpoints), "register_map": register_map, "timeout": 0.5}
        with create(config, name="table") as table:
            table.move_absolute(-2.5)
            reported = table.wait_in_position(timeout=10)
            bound = _bound(twin) + math.pi / register_map["counts_per_rev"]
            assert abs(reported - world.table_angle()) <= bound
            assert abs(reported + 2.5) < 1 * ARCSEC
        wrong_map = create(_config("modbus_tcp", endpoints), name="table")  # default map: gaps
        with pytest.raises(ProtocolError, match="code 2"):
            wrong_map.open()
    finally:
        twin.stop()


def test_factory_builds_each_adapter_and_rejects_bad_configs():
    assert isinstance(create({"adapter": "modbus_tcp", "host": "127.0.0.1"}, name="t"), ModbusTable)
    assert isinstance(create({"adapter": "modbus_rtu", "port": "/dev/null"}, name="t"), ModbusTable)
    table = create(GcsSerialSettings(port="/dev/null", axis="A"), name="t")
    assert isinstance(table, GcsTable) and table.axis == "A" and table.timeout == 0.5
    table = create({"adapter": "gcs_tcp", "host": "127.0.0.1"}, name="t")
    assert isinstance(table, GcsTable) and isinstance(table.settings, GcsTcpSettings)
    assert table.settings.port == 50000 and table.settings.reference_on_open
    with pytest.raises(SettingsError, match=r"^rotary_table 't': unknown adapter 'canopen'; "
                                            r"expected one of modbus_tcp, modbus_rtu, gcs_serial, gcs_tcp$"):
        create({"adapter": "canopen"}, name="t")
    with pytest.raises(SettingsError, match=r"\(modbus_tcp\): setting 'host' is missing"):
        create({"adapter": "modbus_tcp"}, name="t")
    with pytest.raises(SettingsError, match=r"\(gcs_serial\): unknown setting 'unit'; expected one of port, baudrate"):
        create({"adapter": "gcs_serial", "port": "/dev/null", "unit": 3}, name="t")
    with pytest.raises(SettingsError, match=r"unknown setting 'register_map.foo'; expected one of alarm, status"):
        create({"adapter": "modbus_rtu", "port": "/dev/null", "register_map": {"foo": 1}}, name="t")
    with pytest.raises(SettingsError, match="register_map: encoder_position and status both use register 2"):
        create({"adapter": "modbus_rtu", "port": "/dev/null", "register_map": {"status": 2}}, name="t")
    with pytest.raises(SettingsError, match="axis: string should match pattern"):
        create({"adapter": "gcs_serial", "port": "/dev/null", "axis": "1 2"}, name="t")
    with pytest.raises(SettingsError, match="unit 0 is the RTU broadcast address"):
        create({"adapter": "modbus_rtu", "port": "/dev/null", "unit": 0}, name="t")
    with pytest.raises(DeviceConnectionError):
        create({"adapter": "gcs_serial", "port": "/nonexistent/tty"}, name="t").open()
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        free_port = probe.getsockname()[1]
    with pytest.raises(DeviceConnectionError, match=f"open tcp 127.0.0.1:{free_port}"):
        create({"adapter": "gcs_tcp", "host": "127.0.0.1", "port": free_port}, name="t").open()


def test_register_map_is_data_with_partial_groups():
    register_map = RegisterMap.model_validate({"word_order": "little", "status_bits": {"homed": 12}})
    assert register_map.status_bits.homed == 12 and register_map.status_bits.in_position == 3
    assert register_map.opcodes.home == 0x6E
    assert RegisterMap.model_validate(register_map.model_dump()) == register_map
    assert register_map.split32(-2) == [0xFFFE, 0xFFFF] and register_map.join32([0xFFFE, 0xFFFF]) == -2


def test_twins_leak_no_threads_or_fds():
    before_fds = len(os.listdir("/proc/self/fd"))
    before_threads = set(threading.enumerate())
    for _ in range(2):
        world = World()
        twin = RotaryTableTwin(world, {"table": FAST_TABLE})
        endpoints = twin.start()
        for transport in TRANSPORTS:
            with create({**_config(transport, endpoints), "timeout": 0.5}, name="t") as table:
                table.position()
        twin.stop()
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and (set(threading.enumerate()) - before_threads):
        time.sleep(0.05)
    assert not (set(threading.enumerate()) - before_threads)
    assert len(os.listdir("/proc/self/fd")) == before_fds
