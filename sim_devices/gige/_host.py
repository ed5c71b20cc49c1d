"""``GigeTwinHost``: one twin camera as a process of its own (``sim_devices._process.TwinProcess``).

The host object a ``TwinProcess`` builds in its child: it makes the world (a plain seeded ``World``
standalone, or this process's view of a cell's shared world with ``world_dir``), the optical bench
from the same seed and ``optics`` section every process derives alike, and the camera; ``start`` binds
it and returns its endpoints, ``control`` is the camera's control API.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from sim_devices.camera import OpticalBench
from sim_devices.gige._camera import GigeCameraTwin
from sim_devices.world import World, WorldConfig


class GigeTwinHost:
    """Host of one GigE twin camera (``start``/``stop``/``control``).

    Parameters
    ----------
    host : str
        The camera's loopback address.
    camera : mapping, optional
        ``GigeTwinConfig`` fields (``camera``: x, y or z …).
    world : mapping, optional
        ``WorldConfig`` fields (the seed); ignored with ``world_dir`` except as the shared constants.
    optics : mapping, optional
        ``OpticsConfig`` fields.
    world_dir, truth_path : str, optional
        A cell's shared world and truth log (``World.attach``).
    trajectories : str, optional
        The robot's dense truth and controller clock (``<cell>/trajectories``).
    allow_remote : bool
        Serve on an address outside 127.0.0.0/8.
    """

    def __init__(self, host: str, camera: Mapping[str, Any] | None = None, world: Mapping[str, Any] | None = None,
                 optics: Mapping[str, Any] | None = None, world_dir: str | None = None, truth_path: str | None = None,
                 trajectories: str | None = None, allow_remote: bool = False) -> None:
        config = WorldConfig.from_dict(world)
        self.world = World.attach(world_dir, config, truth_path) if world_dir else World(config, truth_path=truth_path)
        self.bench = OpticalBench(self.world, optics)
        self.twin = GigeCameraTwin(self.world, self.bench, host, camera, trajectories=trajectories,
                                   allow_remote=allow_remote)

    def start(self) -> dict[str, Any]:
        return self.twin.start()

    def stop(self) -> None:
        try:
            self.twin.stop()
        finally:
            self.world.close()

    def control(self, command: str, /, **kwargs: Any) -> Any:
        return self.twin.control(command, **kwargs)
