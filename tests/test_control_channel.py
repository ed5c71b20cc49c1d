import pytest

from sim_devices.control import ControlClient, ControlError, ControlServer


@pytest.fixture
def server():
    calls = []

    def handler(command, **args):
        calls.append((command, args))
        if command == "fail":
            raise ValueError("no such axis 'w'")
        return {"command": command, "args": args}

    srv = ControlServer(handler)
    srv.start()
    srv.calls = calls
    yield srv
    srv.stop()


def test_round_trip_and_errors(server):
    client = ControlClient(*server.address, timeout=5)
    assert client.call("mount_on_table", axis="x") == {"command": "mount_on_table", "args": {"axis": "x"}}
    with pytest.raises(ControlError, match="no such axis 'w'"):
        client.call("fail")
    assert server.calls[0] == ("mount_on_table", {"axis": "x"})


def test_refuses_non_loopback():
    with pytest.raises(ValueError, match="loopback"):
        ControlServer(lambda c: None, host="0.0.0.0")


def test_unreachable_cell_is_a_clear_error(server):
    host, port = server.address
    server.stop()
    with pytest.raises(ControlError, match="failed"):
        ControlClient(host, port, timeout=2).call("ping")
    server.stop = lambda: None  # already stopped
