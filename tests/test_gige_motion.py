"""A moving OPR through a GigE twin: each frame is the true pose of its own exposure, blurred by it.

The robot's dense truth is played by a trajectory record the test writes (``sim_devices.trajectory``'s
format, as the UR twin writes it in a cell): the flange moves 0.03 m/s along the base x axis for 1.5 s.
Frames grabbed through Aravis while it moves are compared pixel for pixel with the renderer's image of
the truth at their exposures — the middle pose and the sub-poses of the motion blur computed here from
the same record — and the cross is seen to move from frame to frame.
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from drivers.camera import AravisCamera, AravisSettings, Roi, aravis_available
from sim_devices._transforms import matrix_to_euler, matrix_to_rotvec
from sim_devices.camera import exposure_poses
from sim_devices.trajectory import COLUMNS, TrajectoryLog, encode_header
from tests._gige import Truth, gige_twins, record_of, shared_clock

WHY_NOT = aravis_available()
pytestmark = [pytest.mark.timeout(120),
              pytest.mark.skipif(WHY_NOT is not None, reason=f"Aravis cannot be used here: {WHY_NOT}")]
SPEED = 0.03  # m/s along the base x axis: the cross stays in view over the move (0–45 mm)
MOVE = 1.5  # s
EXPOSURE = 10e-3  # s: 0.3 mm of motion, ≈ 2 px of blur on the screens


def _quaternion(rotation: np.ndarray) -> np.ndarray:
    rotvec = matrix_to_rotvec(rotation)
    angle = float(np.linalg.norm(rotvec))
    axis = rotvec / angle if angle > 0 else np.zeros(3)
    return np.array([np.cos(angle / 2), *(np.sin(angle / 2) * axis)])


def write_motion(directory, truth: Truth, t_start: float, seconds: float) -> None:
    """A closed trajectory record: the flange from its reference pose along +x at ``SPEED``, 1 kHz, for
    ``seconds``; at rest at its end after that."""
    reference = truth.world.reference_flange_pose
    times = t_start + np.arange(0.0, seconds, 1e-3)
    rows = np.zeros((len(times), len(COLUMNS)))
    rows[:, 0] = times
    quaternion = _quaternion(reference[:3, :3])
    for first in (1, 8, 15):  # flange, commanded and encoder poses: one motion here
        rows[:, first:first + 3] = reference[:3, 3] + np.outer(times - t_start, [SPEED, 0.0, 0.0])
        rows[:, first + 3:first + 7] = quaternion
    meta = {"move": 1, "kind": "moveL", "time_scale": 1.0, "control_period": 0.002,
            "tcp_offset": [0, 0, 0, 0, 0, 0], "t_start": t_start}
    (directory / "move-000001.traj").write_bytes(encode_header(meta) + rows.astype("<f8").tobytes())
    (directory / "move-000001.json").write_text(json.dumps({"t_end": float(times[-1])}))


def test_frames_of_a_moving_opr_are_the_truth_of_their_exposures_with_motion_blur(tmp_path):
    truth = Truth()
    trajectories = shared_clock(tmp_path / "trajectories")
    origin = json.loads((trajectories / "clock.json").read_text())["monotonic_origin"]
    log = TrajectoryLog(trajectories)

    def opr_at(times: np.ndarray) -> np.ndarray:
        flange = log.flange_at(times, rest=truth.world.reference_flange_pose)
        return np.linalg.inv(truth.world.base_to_m)[None] @ flange @ truth.world.true_opr_mount[None]

    # Camera z's screen spans M's x and y: the motion moves its cross (screen x would not see it).
    with gige_twins("z", trajectories=trajectories) as (twin,):
        settings = AravisSettings(address=twin.endpoints["host"], exposure_s=EXPOSURE, roi=Roi(0, 0, 1024, 1040))
        with AravisCamera(settings, name="z") as camera:
            t_start = time.monotonic() - origin + 0.5  # the move starts once the camera is ready
            write_motion(trajectories, truth, t_start, MOVE)
            while time.monotonic() - origin < t_start + 0.1:
                time.sleep(0.01)
            frames = []
            while time.monotonic() - origin < t_start + MOVE - 0.1 and len(frames) < 4:
                frames.append(camera.grab(5.0))
                time.sleep(0.1)
        records = [record_of(twin, frame.frame_id) for frame in frames]
    assert len(frames) >= 2
    renderer = truth.renderers[8]
    centres = []
    for frame, record in zip(frames, records):
        assert t_start < record["start"] < t_start + MOVE  # exposed while the OPR moved
        middle, blur = exposure_poses(truth.bench, opr_at, record["start"], record["exposure"], 0.25, 12)
        assert blur is not None and len(blur) >= 8  # 2 px of motion: blurred over ≥ 8 sub-poses
        assert np.allclose(record["opr_in_m"]["t"], middle[:3, 3], rtol=0, atol=1e-12)
        assert np.allclose(record["opr_in_m"]["euler"], matrix_to_euler(middle[:3, :3]), rtol=0, atol=1e-12)
        expected = renderer.render("z", middle, seq=record["seq"], roi=tuple(record["roi"]), blur=blur,
                                   exposure_scale=record["exposure"] / 1e-3)
        assert np.array_equal(frame.image, expected)
        sharp = renderer.render("z", middle, seq=record["seq"], roi=tuple(record["roi"]),
                                exposure_scale=record["exposure"] / 1e-3)
        assert not np.array_equal(frame.image, sharp)  # the blur is in the frame
        centres.append(middle[:3, 3])
    # The OPR moved between the frames by the truth's speed × the time between their exposures.
    steps = np.linalg.norm(np.diff(np.array(centres), axis=0), axis=1)
    gaps = np.diff([r["start"] for r in records])
    assert np.allclose(steps, SPEED * gaps, rtol=1e-6)
