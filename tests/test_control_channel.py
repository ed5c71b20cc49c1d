import json
import socket

import pytest

from sim_devices.control import ControlClient, ControlError, ControlServer, dispatch


@pytest.fixture
def server():
    calls = []

    def handler(command, /, **args):
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


def test_a_request_may_carry_a_command_of_its_own(server):
    """``command`` is positional-only on both ends, so a forwarded twin command travels in the args."""
    client = ControlClient(*server.address, timeout=5)
    result = client.call("device", device="interferometer", command="arm", kind="beam_break")
    assert result == {"command": "device", "args": {"device": "interferometer", "command": "arm",
                                                    "kind": "beam_break"}}


@pytest.mark.parametrize("line, error", [
    (b"not json\n", "request is not JSON"),
    (b'{"args": {}}\n', "request has no command"),
    (b'["ping"]\n', "request has no command"),
    (b'{"command": "ping", "args": [1]}\n', "args of 'ping' must be an object"),
])
def test_malformed_requests_get_an_error_reply_and_the_connection_lives_on(server, line, error):
    with socket.create_connection(server.address, timeout=5) as sock:
        reader = sock.makefile("rb")
        sock.sendall(line)
        reply = json.loads(reader.readline())
        assert not reply["ok"] and error in reply["error"]
        sock.sendall(b'{"command": "ping"}\n')
        assert json.loads(reader.readline()) == {"ok": True, "result": {"command": "ping", "args": {}}}


def test_dispatch_names_the_known_commands_and_the_expected_arguments():
    calls = []

    def mount(axis: str, depth: float = 0.0) -> str:
        calls.append((axis, depth))
        return axis

    table = {"mount": mount, "ping": lambda: "pong"}
    assert dispatch(table, "mount", {"axis": "x"}, "cell") == "x"
    assert dispatch(table, "ping", {}, "cell") == "pong"
    with pytest.raises(ValueError, match="cell: unknown command 'mout'; expected one of mount, ping"):
        dispatch(table, "mout", {}, "cell")
    with pytest.raises(ValueError, match=r"cell: bad arguments for mount\(axis, depth=0.0\): missing .* 'axis'"):
        dispatch(table, "mount", {}, "cell")
    with pytest.raises(ValueError, match=r"unexpected keyword argument 'axes'"):
        dispatch(table, "mount", {"axis": "x", "axes": "x"}, "cell")
    assert calls == [("x", 0.0)]  # a refused call never reached the method
