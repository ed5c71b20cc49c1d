"""``python -m sim_devices.gige --host 127.A.B.N``: one camera, the OPR at rest, for Aravis's own tools.

Started as a process by the fixture (and stopped by SIGTERM, its clean stop): Aravis's ``arv-tool``
lists its features, and the adapter grabs the laser cross — software-triggered and free-running —
pixel-exact the renderer's image of the reference pose.
"""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest

from drivers.camera import AravisCamera, AravisSettings, aravis_available
from sim_devices.cell import free_loopback_host
from tests._gige import SEED, Truth

WHY_NOT = aravis_available()
pytestmark = [pytest.mark.timeout(120),
              pytest.mark.skipif(WHY_NOT is not None, reason=f"Aravis cannot be used here: {WHY_NOT}")]


class _Standalone:
    """The standalone twin's process. It has no control channel, so the truth is the test's own
    renderer at the noise seq its frame ids imply."""

    def __init__(self, host: str) -> None:
        self.host = host
        self.process = subprocess.Popen([sys.executable, "-m", "sim_devices.gige", "--host", host, "--camera", "y",
                                         "--seed", str(SEED)], stdout=subprocess.PIPE, text=True)

    def endpoints(self) -> dict:
        assert self.process.stdout is not None
        line = self.process.stdout.readline()  # printed once bound
        assert line, "the standalone twin exited before serving"
        return json.loads(line)

    def stop(self) -> int:
        self.process.send_signal(signal.SIGTERM)
        try:
            return self.process.wait(15.0)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait(5.0)
            return -9


@pytest.fixture()
def standalone():
    twin = _Standalone(free_loopback_host(2, 254, tcp_ports=(), udp_ports=(3956,)))
    try:
        yield twin
    finally:
        assert twin.stop() == 0


def test_the_standalone_twin_serves_the_reference_pose_to_arv_tool_and_the_adapter(standalone):
    endpoints = standalone.endpoints()
    assert endpoints["host"] == standalone.host and endpoints["camera"] == "y"
    tool = shutil.which("arv-tool-0.8")
    if tool is not None:
        listed = subprocess.run([tool, "-a", standalone.host, "features"], capture_output=True, text=True, timeout=30)
        assert "TriggerSource" in listed.stdout and "ExposureTime" in listed.stdout
    truth = Truth()
    with AravisCamera(AravisSettings(address=standalone.host), name="y") as camera:
        triggered = camera.grab(5.0)
        camera.configure(software_trigger=False)  # free run at AcquisitionFrameRate (10 Hz)
        free = [camera.grab(5.0) for _ in range(2)]
    for frame in (triggered, *free):
        # The standalone twin numbers its exposures from 1 (its renderer primed with seq 0): frame id n
        # is exposure n, noise seq 2^44 + n, the reference pose, 1 ms.
        record = {"camera": "y", "seq": (1 << 44) + frame.frame_id, "roi": [0, 0, 1024, 1040],
                  "exposure": 1e-3, "pixel_format": "Mono8"}
        assert np.array_equal(frame.image, truth.frame(record))
    assert free[1].frame_id > free[0].frame_id and free[0].image.max() >= 200  # the cross is in view
