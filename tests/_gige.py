"""Shared pieces of the GigE Vision tests: twin cameras in processes of their own, and the truth.

Every twin is a ``TwinProcess`` (``sim_devices.gige.GigeTwinHost``) on a loopback address taken
with ``free_loopback_host`` (UDP 3956 free; the block from ``SIM_LOOPBACK_BLOCK``); the fixture that
starts it stops it. The twins of one test share a controller clock (a ``clock.json`` the test
writes, as the robot twin does in a cell), so line pulses and action times line up across them.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from sim_devices._process import TwinProcess, TwinProcessError
from sim_devices.camera import OpticalBench, Renderer
from sim_devices.cell import free_loopback_host
from sim_devices.gige import pixel_bytes
from sim_devices.world import World, WorldConfig

SEED = 3
GVCP_UDP = (3956,)


def shared_clock(directory: Path) -> Path:
    """A trajectory directory whose ``clock.json`` puts the controller clock's origin now."""
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "clock.json").write_text(json.dumps({"monotonic_origin": time.monotonic(), "period": 0.002,
                                                      "time_scale": 1.0}))
    return directory


@contextmanager
def gige_twins(cameras: Sequence[str], trajectories: Path | None = None, **config: Any) -> Iterator[list[TwinProcess]]:
    """One twin process per camera name (x, y, z), each on its own free loopback address; launched
    together (their start-ups overlap), stopped by the context's end."""
    taken: list[str] = []
    launched: list[TwinProcess] = []

    def launch(camera: str) -> TwinProcess:
        host = free_loopback_host(2, 254, exclude=tuple(taken), tcp_ports=(), udp_ports=GVCP_UDP)
        taken.append(host)
        twin = TwinProcess("sim_devices.gige:GigeTwinHost",
                           {"host": host, "camera": {"camera": camera, **config}, "world": {"seed": SEED},
                            "trajectories": None if trajectories is None else str(trajectories)},
                           start_timeout=60.0, call_timeout=30.0, name=f"gige twin {camera}")
        twin.launch()
        launched.append(twin)
        return twin

    try:
        pending = [(camera, launch(camera)) for camera in cameras]
        started = []
        for camera, twin in pending:
            for _attempt in range(5):  # another test may bind the address between the check and ours
                try:
                    twin.wait_started()
                    break
                except TwinProcessError as error:
                    if "cannot bind" not in str(error):
                        raise
                    twin = launch(camera)
            else:
                raise RuntimeError(f"no free loopback address for gige twin {camera}")
            started.append(twin)
        yield started
    finally:
        for twin in launched:
            twin.stop()


class Truth:
    """The twins' world as the test sees it: the same seed gives the same optics and noise."""

    def __init__(self) -> None:
        self.world = World(WorldConfig(seed=SEED))
        self.bench = OpticalBench(self.world)
        # Primed like the twin's (one full frame first): the background-noise pool then has the twin's size.
        self.renderers = {depth: Renderer(self.bench, seed=SEED, bit_depth=depth) for depth in (8, 12)}
        for renderer in self.renderers.values():
            renderer.render("x", self.world.state().opr_in_m, seq=0)

    def frame(self, record: dict[str, Any]) -> np.ndarray:
        """The image a frame record says was rendered (the OPR at rest: no blur), as the format carries it."""
        fmt = record["pixel_format"]
        image = self.renderers[8 if fmt == "Mono8" else 12].render(
            record["camera"], self.world.state().opr_in_m, seq=record["seq"], roi=tuple(record["roi"]),
            exposure_scale=record["exposure"] / 1e-3)
        dtype = np.uint8 if fmt == "Mono8" else np.dtype("<u2")
        return np.frombuffer(pixel_bytes(image, fmt), dtype=dtype).reshape(record["roi"][3], record["roi"][2])


def record_of(twin: TwinProcess, block_id: int, timeout: float = 10.0) -> dict[str, Any]:
    """The twin's truth of the frame it sent as ``block_id`` (the latest with that id)."""
    deadline = time.monotonic() + timeout
    while True:
        matches = [r for r in twin.call("frames", last=500) if r["block_id"] == block_id]
        if matches:
            return matches[-1]
        if time.monotonic() > deadline:
            raise AssertionError(f"no frame record with block id {block_id}")
        time.sleep(0.01)
