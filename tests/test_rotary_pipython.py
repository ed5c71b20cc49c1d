"""PI's own GCS client (``pipython``) against the table twin's GCS faces: an outside check of the twin.

pipython is proprietary, so it is never a dependency of this project: this test runs only where it
can be imported, e.g. after ``pip install --target /tmp/pipython-pkg pipython pyusb`` with
``PYTHONPATH=/tmp/pipython-pkg``. Its pure-Python gateways (``PISocket`` for TCP, ``PISerial`` over
pyserial) need no vendor library.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator

import pytest

from sim_devices import World
from sim_devices.rotary_table import RotaryTableTwin

pipython = pytest.importorskip("pipython", reason="pipython (proprietary, not a dependency) is not installed")
from pipython.pidevice.gcscommands import GCSCommands  # noqa: E402
from pipython.pidevice.gcsmessages import GCSMessages  # noqa: E402
from pipython.pidevice.interfaces.piserial import PISerial  # noqa: E402
from pipython.pidevice.interfaces.pisocket import PISocket  # noqa: E402

pytestmark = pytest.mark.timeout(60)
FAST_TABLE = {"max_speed": 3.0, "peak_torque": 1.0, "home_speed": 3.0, "seed": 9}


@pytest.fixture
def twin() -> Iterator[tuple[World, RotaryTableTwin, dict]]:
    world = World()
    world.mount_on_table("z")
    twin = RotaryTableTwin(world, {"transports": ["gcs", "gcs_tcp"], "table": FAST_TABLE})
    endpoints = twin.start()
    yield world, twin, endpoints
    twin.stop()
    world.truth.close()


def _until(predicate, what: str, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


@pytest.mark.parametrize("face", ["gcs_tcp", "gcs"])
def test_pipython_sets_up_and_moves_the_table(twin, face):
    world, table, endpoints = twin
    gateway = (PISocket(host="127.0.0.1", port=endpoints["gcs_tcp_port"]) if face == "gcs_tcp"
               else PISerial(endpoints["gcs_port"], 115200))
    with gateway, GCSCommands(GCSMessages(gateway)) as pidevice:
        assert pidevice.qCSV() == 2.0 and pidevice.qSAI() == ["1"]
        assert not pidevice.qSVO("1")["1"] and not pidevice.qFRF("1")["1"]  # power-on state
        with pytest.raises(pipython.GCSError) as refused:
            pidevice.MOV("1", 10.0)
        assert refused.value.val == 5
        pidevice.SVO("1", True)
        pidevice.FRF("1")
        _until(lambda: pidevice.qFRF("1")["1"] and pidevice.qONT("1")["1"], "referenced")
        pidevice.MOV("1", 10.0)
        _until(lambda: pidevice.qONT("1")["1"], "on target")
        _until(lambda: world.state().settled and table.physics.settled(), "settled")
        bound = math.degrees(table.table_config.reported_error_bound())
        assert abs(pidevice.qPOS("1")["1"] - math.degrees(world.table_angle())) <= bound
        with pytest.raises(pipython.GCSError) as refused:
            pidevice.MOV("1", 40_000.0)
        assert refused.value.val == 7
        assert pidevice.qTMX("1")["1"] == 36_000.0
