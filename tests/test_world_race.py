"""The race that let a wrong frame be measured: a settled state overtaken by a moving one.

A process that acknowledges a settled seq must first have called its subscribers with THAT settled
state's data. The unit tests pause a subscriber process at a chosen point (its callback waits on a
gate the test opens through the control pipe), write the states around it and check what it was
given and when the settled write returned. The stress test runs a real cell under two CPU burners
with the camera twin slowed and checks, after every "done" of the real driver, that the frames on
disk are those of the settled state the robot reported.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time

import numpy as np
import pytest

from sim_devices import TwinProcess
from sim_devices.world import World, WorldConfig


class GatedSubscriber:
    """A subscriber in another process whose callback, while the gate is closed, blocks in it."""

    def __init__(self, world_dir: str, seed: int) -> None:
        self.world = World.attach(world_dir, WorldConfig(seed=seed))
        self.gate = threading.Event()
        self.gate.set()
        self.blocked_in: int | None = None
        self.seen: list[dict] = []

    def _on_state(self, state) -> None:
        began = time.monotonic()
        if not self.gate.is_set():
            self.blocked_in = state.seq
            self.gate.wait(30.0)
            self.blocked_in = None
        self.seen.append({"seq": state.seq, "settled": state.settled, "began": began, "ended": time.monotonic(),
                          "flange": state.flange_pose.tolist()})

    def start(self) -> dict:
        self.world.subscribe(self._on_state)
        return {"pid": os.getpid()}

    def stop(self) -> None:
        self.gate.set()
        self.world.unsubscribe(self._on_state)
        self.world.close()

    def control(self, command: str, /, **kwargs):
        if command == "close_gate":
            self.gate.clear()
        elif command == "open_gate":
            self.gate.set()
        elif command == "blocked_in":
            return self.blocked_in
        elif command == "seen":
            return list(self.seen)
        elif command == "acks":
            channel = self.world.channel
            assert channel is not None
            return {pid: ack for _slot, pid, ack in channel.subscribers()}
        else:
            raise ValueError(command)
        return None


def _wait_for(predicate, timeout=20.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.01)


def _moved(world: World, dx: float) -> np.ndarray:
    pose = world.flange_pose()
    pose[0, 3] += dx
    return pose


@pytest.fixture
def shared(tmp_path):
    world = World(WorldConfig(seed=3), truth_path=tmp_path / "truth.jsonl")
    world_dir = str(world.share(tmp_path / "world"))
    subscriber = TwinProcess("tests.test_world_race:GatedSubscriber", {"world_dir": world_dir, "seed": 3})
    subscriber.start()
    try:
        yield world, subscriber
    finally:
        subscriber.stop()
        world.close()


def _publish_settled_in_background(world: World, pose: np.ndarray) -> tuple[threading.Thread, dict]:
    """``set_flange_pose(pose)`` (settled: it waits for the acks) on a thread; the result says when it returned."""
    result: dict = {}

    def publish() -> None:
        result["state"] = world.set_flange_pose(pose)
        result["returned"] = time.monotonic()

    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    return thread, result


def test_a_settled_state_overtaken_by_a_moving_one_is_delivered_with_its_own_data(shared):
    world, subscriber = shared
    subscriber.call("close_gate")
    first = world.set_flange_pose(_moved(world, 0.001), settled=False)
    _wait_for(lambda: subscriber.call("blocked_in") == first.seq)  # paused in the callback of a moving state

    settled_pose = _moved(world, 0.010)
    publisher, result = _publish_settled_in_background(world, settled_pose)
    _wait_for(lambda: world.state().settled)
    passing = world.set_flange_pose(_moved(world, 0.00003), settled=False)  # 30 µm on: the next move begins
    assert publisher.is_alive()  # the settled write still waits for the paused process
    subscriber.call("open_gate")
    publisher.join(30.0)
    assert not publisher.is_alive()

    settled = result["state"]
    seen = {entry["seq"]: entry for entry in subscriber.call("seen")}
    # The settled state itself, with the pose it settled at, was delivered before its write returned ...
    assert seen[settled.seq]["settled"]
    np.testing.assert_array_equal(seen[settled.seq]["flange"], settled_pose)
    assert seen[settled.seq]["ended"] <= result["returned"]
    # ... and the pose the robot was passing through afterwards is delivered as what it is: moving.
    _wait_for(lambda: passing.seq in {e["seq"] for e in subscriber.call("seen")})
    later = [e for e in subscriber.call("seen") if e["seq"] == passing.seq][0]
    assert not later["settled"]
    np.testing.assert_array_equal(later["flange"], passing.flange_pose)


# ------------------------------------------------------------------------------ a real cell under load
def _burn() -> None:
    while True:
        pass


@pytest.fixture
def two_cpu_burners():
    """Two processes spinning at full speed (the machine saturated, as when the race was seen)."""
    context = multiprocessing.get_context("spawn")
    burners = [context.Process(target=_burn, daemon=True) for _ in range(2)]
    for burner in burners:
        burner.start()
    try:
        yield burners
    finally:
        for burner in burners:
            burner.terminate()
        for burner in burners:
            burner.join(10.0)


@pytest.mark.slow
def test_after_every_done_the_frames_show_that_settled_pose_under_load(tmp_path, two_cpu_burners):
    pytest.importorskip("rtde_control")
    import yaml

    from drivers.robot import MotionEnvelope, create
    from sim_devices.cell import SimCell

    moves = 40
    with SimCell(seed=4, directory=tmp_path / "cell", time_scale=4.0,
                 config={"cameras": {"render_delay": 0.05}}) as cell:
        station = yaml.safe_load(cell.station_path.read_text())
        robot = create({**station["devices"]["robot"], "connect_timeout": 10.0, "move_timeout": 30.0},
                       name="robot", envelope=MotionEnvelope.from_dict(station["envelope"]))
        robot.open()
        try:
            robot.set_tcp(np.array(station["frames"]["tcp_offset"]))
            reference = np.array(station["frames"]["reference_tcp_pose"])
            stale = []
            for move in range(moves):
                target = reference.copy()
                target[:3] += [0.002 * (move % 3), 0.003 * (move % 4), 0.001 * (move % 2)]
                robot.move_linear(target, speed=0.25, acceleration=1.2)
                # Done: the frames on disk must be those of the settled pose the robot just reported.
                pose = cell.truth("pose", last=1)[0]
                frames = cell.truth("frames", last=1)[0]
                if frames["seq"] != pose["seq"] or not np.allclose(frames["opr_in_m"]["t"], pose["opr_in_m"]["t"],
                                                                   rtol=0.0, atol=1e-12):
                    stale.append((move, pose["seq"], frames["seq"]))
            assert stale == []
            assert len(cell.truth("pose")) >= moves
        finally:
            robot.close()
