"""Twin-process hosts for the shared-world tests: a subscriber and a writer in another process."""

from __future__ import annotations

import os
import threading
import time

import numpy as np

from sim_devices.world import World, WorldConfig


class WorldSubscriber:
    """Attaches to a shared world and records every delivery; each callback takes ``delay`` seconds."""

    def __init__(self, world_dir: str, seed: int, delay: float = 0.0, truth_path: str | None = None) -> None:
        self.world = World.attach(world_dir, WorldConfig(seed=seed), truth_path)
        self.delay = float(delay)
        self.seen: list[dict] = []
        self.announced: list[list[list[float]]] = []

    def _on_state(self, state) -> None:
        began = time.monotonic()
        time.sleep(self.delay)
        self.seen.append({"seq": state.seq, "settled": state.settled, "began": began, "ended": time.monotonic(),
                          "flange": state.flange_pose.tolist()})

    def start(self) -> dict:
        self.world.subscribe(self._on_state)
        self.world.on_announce(lambda expected: self.announced.append(expected.flange_pose.tolist()))
        return {"pid": os.getpid()}

    def stop(self) -> None:
        self.world.unsubscribe(self._on_state)
        self.world.close()

    def control(self, command: str, /, **kwargs):
        if command == "seen":
            return list(self.seen)
        if command == "announced":
            return list(self.announced)
        if command == "opr_in_m":
            return self.world.opr_in_m().tolist()
        if command == "move":  # a settled publish from this process
            pose = self.world.flange_pose()
            pose[:3, 3] += kwargs["delta"]
            return self.world.set_flange_pose(pose, source="subscriber").seq
        raise ValueError(command)


class WorldWriter:
    """Attaches to a shared world and, once started, alternates the flange between two poses, unsettled."""

    def __init__(self, world_dir: str, seed: int) -> None:
        self.world = World.attach(world_dir, WorldConfig(seed=seed))
        self.poses = [self.world.flange_pose(), self.world.flange_pose()]
        self.poses[1][:3, :3] = self.poses[1][:3, :3] @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        self.poses[1][:3, 3] += [0.01, -0.02, 0.03]
        self.writes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._write, daemon=True)

    def _write(self) -> None:
        while not self._stop.is_set():
            self.world.set_flange_pose(self.poses[self.writes % 2], settled=False)
            self.writes += 1

    def start(self) -> dict:
        self._thread.start()
        return {"poses": [p.tolist() for p in self.poses]}

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.world.close()

    def control(self, command: str, /, **kwargs):
        if command == "writes":
            return self.writes
        raise ValueError(command)
