"""The engine on the fake cell: the three procedures, dry run, pause/resume, protective stop, abort."""

import json
import threading
import time

import numpy as np
import pytest

from procedures.engine import open_engine
from procedures.report import export_json, render_report
from procedures.station import RunError, tcp_in_m
from tests.fakes import REFERENCE_TCP, FakeCell, FakeScience, write_station


def _procedure(tmp_path, kind, **params):
    body = ", ".join(f"{k}: {v}" for k, v in {"settle_time_s": 0, "frames_per_pose": 1, **params}.items())
    path = tmp_path / f"{kind}.yaml"
    path.write_text(f"procedure: {kind}\nparameters: {{{body}}}\n")
    return path


@pytest.fixture
def setup(tmp_path):
    truth = tmp_path / "truth.jsonl"
    station = write_station(tmp_path / "station.yaml", truth_log=str(truth))
    cell = FakeCell(seed=2, truth_log=truth)
    return tmp_path, station, cell


def _engine(tmp_path, station, cell, procedure=None, run_id=None, **kwargs):
    return open_engine(tmp_path / "runs", procedure=procedure, station=station, run_id=run_id,
                       science=FakeScience(cell), devices=cell.devices(), operator=cell.operator, **kwargs)


def _states(store, run_id):
    return [e["message"].split(":")[0] for e in store.events(run_id) if e["kind"] == "state"]


def test_iso_run_matches_truth(setup):
    tmp_path, station, cell = setup
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=12)
    with _engine(tmp_path, station, cell, proc) as engine:
        assert engine.execute() == "FINISHED"
        run = engine.store.get_run(engine.run_id)
        samples = engine.store.samples(engine.run_id)
    assert len(samples) == run["total_steps"] == 5 + 12 * 5
    results = run["results"]
    assert results["order"] == ["P1", "P5", "P4", "P3", "P2"]
    assert [s.label for s in samples[5:10]] == ["P1", "P5", "P4", "P3", "P2"]
    for label in results["order"]:
        point = results["points"][label]
        assert point["n"] == 12
        # Measured and true RP_l differ only by the fake instrument's noise (0.3 µm) and the slope of
        # its systematic error (≤ 2.5e-3 × scatter): well under 1 µm for ~20 µm figures.
        assert point["stats"]["rp_l"] == pytest.approx(point["true_stats"]["rp_l"], abs=1e-6)
        # Robot repeatability σ = 5 µm per axis, plus 2e-5 rad × 0.07 m lever: RP_l ≈ 3.5σ_eff.
        assert 8e-6 < point["stats"]["rp_l"] < 40e-6


def test_calibration_runs_write_records(setup):
    tmp_path, station, cell = setup
    for kind in ("displacement_calibration", "angle_calibration"):
        proc = _procedure(tmp_path, kind, repeats=2)
        with _engine(tmp_path, station, cell, proc) as engine:
            assert engine.execute() == "FINISHED"
            run = engine.store.get_run(engine.run_id)
        results = run["results"]
        assert run["calibration_record_id"] == results["record_id"]
        assert (tmp_path / "runs" / run["id"] / f"calibration-{kind.split('_')[0]}.json").is_file()
        for name, curve in results["curves"].items():
            before, after = np.abs(curve["error_before"]).max(), np.abs(curve["error_after"]).max()
            assert after < before / 5, (name, before, after)
    assert cell.log == ["align x", "align y", "align z", "mount table:x", "mount table:y", "mount table:z",
                        "mount robot"]


def test_displacement_reference_is_interferometer_relative_to_group_start(setup):
    tmp_path, station, cell = setup
    proc = _procedure(tmp_path, "displacement_calibration", axes="[y]", repeats=2)
    with _engine(tmp_path, station, cell, proc) as engine:
        engine.execute()
        samples = engine.store.samples(engine.run_id)
    for s in samples:
        # the reference is the nominal start plus the interferometer reading; it must follow the
        # commanded position to within the robot's repeatability
        assert s.reference.value == pytest.approx(s.meta["nominal"], abs=40e-6)


def test_dry_run_refuses_targets_outside_the_envelope(setup):
    tmp_path, station, cell = setup
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2, cube_center_m="[0.035, 0.035, 0.3]")
    with _engine(tmp_path, station, cell, proc) as engine:
        assert engine.execute() == "FAILED"
        run = engine.store.get_run(engine.run_id)
    assert "dry run failed" in run["reason"] and "outside the envelope" in run["reason"]
    assert "transform/c000/P1" in run["reason"]
    assert cell.moves == 0


def test_dry_run_checks_crosses_on_screens(setup):
    tmp_path, station, cell = setup
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2, cube_center_m="[0.035, 0.12, 0.035]")
    with _engine(tmp_path, station, cell, proc) as engine:
        assert engine.execute() == "FAILED"
        assert "cross off screen" in engine.store.get_run(engine.run_id)["reason"]
    assert cell.moves == 0


def test_pause_and_resume_at_a_safe_point(setup):
    tmp_path, station, cell = setup
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=3)
    paused = threading.Event()

    def listener(event):
        if event["event"] == "progress" and event["done"] == 4:
            engine.request_pause("test")
        if event["event"] == "state" and event["state"] == "PAUSED":
            paused.set()

    def resumer():
        assert paused.wait(30)
        engine.resume()

    with _engine(tmp_path, station, cell, proc, listener=listener) as engine:
        thread = threading.Thread(target=resumer)
        thread.start()
        assert engine.execute() == "FINISHED"
        thread.join()
        assert _states(engine.store, engine.run_id) == ["RUNNING", "PAUSED", "RUNNING", "FINISHED"]
        assert len(engine.store.samples(engine.run_id)) == 20


def test_detached_pause_continues_later_without_duplicates(setup):
    tmp_path, station, cell = setup
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=3)

    def listener(event):
        if event["event"] == "progress" and event["done"] == 7:
            engine.request_pause("end of shift")

    with _engine(tmp_path, station, cell, proc, listener=listener, pause_timeout_s=0.1) as engine:
        assert engine.execute() == "PAUSED"
        run_id = engine.run_id
        assert engine.store.committed_steps(run_id) == set(range(7))
    with _engine(tmp_path, None, cell, run_id=run_id) as engine:
        assert engine.execute() == "FINISHED"
        assert [s.step_index for s in engine.store.samples(run_id)] == list(range(20))


def test_protective_stop_pauses_and_retries_the_step(setup):
    tmp_path, station, cell = setup
    cell.protective_stop_on_moves = {6}
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2)

    def handler(engine):
        assert engine.state == "PAUSED"
        cell.robot.clear_protective_stop()  # the operator clears the stop, then resumes
        return "resume"

    with _engine(tmp_path, station, cell, proc, pause_handler=handler) as engine:
        assert engine.execute() == "FINISHED"
        events = engine.store.events(engine.run_id)
        samples = engine.store.samples(engine.run_id)
    assert any(e["kind"] == "state" and "ProtectiveStop" in e["message"] for e in events)
    assert [s.step_index for s in samples] == list(range(15))
    assert cell.robot.stops >= 1


def test_abort_while_paused_brings_devices_to_a_safe_state(setup):
    tmp_path, station, cell = setup
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2)

    def listener(event):
        if event["event"] == "progress" and event["done"] == 3:
            engine.request_pause()

    with _engine(tmp_path, station, cell, proc, listener=listener, pause_handler=lambda e: "abort") as engine:
        assert engine.execute() == "ABORTED"
        assert engine.store.get_run(engine.run_id)["exit_status"] == "abort"
        with pytest.raises(RunError):
            engine.execute()  # an aborted run is final
    assert cell.robot.stops >= 1


def test_keyboard_interrupt_during_a_move_aborts(setup):
    tmp_path, station, cell = setup
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2)
    original = cell.robot.move_linear

    def interrupted(pose, *args, **kwargs):
        if cell.moves == 4:
            raise KeyboardInterrupt("second Ctrl-C")
        return original(pose, *args, **kwargs)

    cell.robot.move_linear = interrupted
    with _engine(tmp_path, station, cell, proc) as engine:
        assert engine.execute() == "ABORTED"
        assert len(engine.store.samples(engine.run_id)) == 4
    assert cell.robot.stops >= 1


def test_failed_measurements_are_recorded_with_their_frames(setup):
    tmp_path, station, cell = setup
    cell.fail_measures = 3  # the first pose fails on every attempt (retries_per_pose = 2)
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2, retry_backoff_s=0)
    with _engine(tmp_path, station, cell, proc) as engine:
        assert engine.execute() == "FINISHED"
        samples = engine.store.samples(engine.run_id)
        run_dir = engine.store.run_dir(engine.run_id)
    assert not samples[0].ok and "no cross found" in samples[0].error
    assert len(samples[0].frames) == 9 and all((run_dir / f).is_file() for f in samples[0].frames)
    assert all(s.ok for s in samples[1:])


@pytest.mark.parametrize("stale_triples", [1, 3])
def test_a_frame_of_the_previous_pose_is_measured_again_and_never_stored_as_good(setup, stale_triples):
    """The cameras still show the previous pose after the robot reported the new one (a stale frame): the
    pose is 35 mm from where the robot was sent, so the attempt fails and the pose is measured again; if
    every attempt sees it, the sample fails (a resume measures it again) instead of being committed."""
    tmp_path, station, cell = setup
    cell.stale_after_moves = {3: stale_triples}  # the third move (P4 of the transform pass): P5's frames
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2, retry_backoff_s=0, frames_per_pose=1)
    with _engine(tmp_path, station, cell, proc) as engine:
        assert engine.execute() == "FINISHED"
        samples = engine.store.samples(engine.run_id)
        events = [e["message"] for e in engine.store.events(engine.run_id) if e["kind"] == "measure_failed"]
    caught = [m for m in events if "not where the devices were sent" in m and "stale or wrong frame" in m]
    assert len(caught) == stale_triples and all(m.startswith(samples[2].step_key) for m in caught)
    assert [s.ok for s in samples] == [True, True, stale_triples < 3, *[True] * (len(samples) - 3)]
    if stale_triples < 3:  # measured again: the pose of P4, not of P5
        p4 = [s.solved.pose[:3] for s in samples if s.label == "P4"]
        assert len(p4) == 3 and np.all(np.ptp(p4, axis=0) < 1e-3)  # within a mm (P5 is 35 mm away)
    else:
        assert "stale or wrong frame" in samples[2].error


def test_without_the_plausibility_check_a_stale_frame_would_be_stored_as_good(setup):
    """The check above is what catches it: with the limits at 0 (not checked) the same stale triple is
    committed as a good P4 sample 35 mm from the others."""
    tmp_path, station, cell = setup
    cell.stale_after_moves = {3: 1}
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2, frames_per_pose=1, plausibility_mm=0,
                      plausibility_deg=0)
    with _engine(tmp_path, station, cell, proc) as engine:
        assert engine.execute() == "FINISHED"
        samples = engine.store.samples(engine.run_id)
    assert samples[2].ok and samples[2].label == "P4"
    p4 = [s.solved.pose[:3] for s in samples if s.label == "P4"]
    assert np.max(np.ptp(p4, axis=0)) > 10e-3


def test_too_many_failures_fail_the_run(setup):
    tmp_path, station, cell = setup
    cell.fail_grabs = 100
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2, max_failed_samples=1, retries_per_pose=0)
    with _engine(tmp_path, station, cell, proc) as engine:
        assert engine.execute() == "FAILED"
        run = engine.store.get_run(engine.run_id)
    assert "max_failed_samples" in run["reason"]
    assert run["exit_status"] == "fail"


def test_interferometer_is_aligned_where_each_line_starts(setup):
    """The operator aims the interferometer at the reflector, so the robot must already stand at the
    line's first point when asked (the InterferometerAligned set-up comes after the step's motion)."""
    tmp_path, station, cell = setup
    aligned_at = {}
    align = cell.operator.align_interferometer

    def recording_align(axis):
        aligned_at[axis] = tcp_in_m(REFERENCE_TCP, cell.robot.tcp_pose())[:3, 3]
        align(axis)

    cell.operator.align_interferometer = recording_align
    proc = _procedure(tmp_path, "displacement_calibration", axes="[y, z]", repeats=2, start_mm=10)
    with _engine(tmp_path, station, cell, proc) as engine:
        assert engine.execute() == "FINISHED"
    for axis, position in aligned_at.items():
        expected = np.zeros(3)
        expected["xyz".index(axis)] = 0.010  # group 0 starts at M's origin, its line at start_mm
        np.testing.assert_allclose(position, expected, atol=1e-12)
    assert list(aligned_at) == ["y", "z"]


# ------------------------------------------------------------------ issue 12: resume always finishes
def test_failed_poses_are_measured_again_on_resume_and_kept_as_superseded(setup):
    tmp_path, station, cell = setup
    cell.fail_measures = 3  # the first pose fails on all three attempts
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2, max_failed_samples=0, retry_backoff_s=0)
    with _engine(tmp_path, station, cell, proc) as engine:
        assert engine.execute() == "FAILED"
        run = engine.store.get_run(engine.run_id)
    assert "1 poses could not be measured in this session" in run["reason"]
    assert "transform/c000/P1: attempt 3: screen y: no cross found (fake)" in run["reason"]
    with _engine(tmp_path, None, cell, run_id=run["id"]) as engine:
        assert engine.execute() == "FINISHED"
        samples = engine.store.samples(run["id"])
        superseded = engine.store.superseded_samples(run["id"])
        events = engine.store.events(run["id"])
        finished = engine.store.get_run(run["id"])
    assert [s.step_index for s in samples] == list(range(15)) and all(s.ok for s in samples)
    exported = json.loads(export_json(finished, samples, events, superseded))
    assert [s["step_key"] for s in exported["superseded_samples"]] == ["transform/c000/P1"]
    assert "measured again later" in render_report(finished, samples, events, superseded)
    assert [(s.step_index, s.ok) for s in superseded] == [(0, False)]  # the failure is kept, not lost
    assert "no cross found" in superseded[0].error
    assert any(e["kind"] == "remeasured" and e["message"].startswith("transform/c000/P1") for e in events)
    assert "1 failed poses to measure again" in [e for e in events if e["kind"] == "state"][-2]["message"]


def test_max_failed_samples_counts_the_failures_of_one_session(setup):
    tmp_path, station, cell = setup
    cell.fail_measures = 2  # poses 0 and 1 fail (one attempt each)
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2, max_failed_samples=1, retries_per_pose=0)
    with _engine(tmp_path, station, cell, proc) as engine:
        assert engine.execute() == "FAILED"  # the second failure of this session is one too many
        run_id = engine.run_id
    cell.fail_measures = 1  # on resume, pose 0 fails again: the only failure of this session, tolerated
    with _engine(tmp_path, None, cell, run_id=run_id) as engine:
        assert engine.execute() == "FINISHED"
        samples = engine.store.samples(run_id)
        superseded = engine.store.superseded_samples(run_id)
    assert [s.step_index for s in samples] == list(range(15))
    assert [s.step_index for s in samples if not s.ok] == [0]
    assert sorted(s.step_index for s in superseded) == [0, 1]


def test_retries_back_off(setup):
    tmp_path, station, cell = setup
    cell.fail_grabs = 2  # the first two attempts of the first pose fail
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2, retry_backoff_s=0.3)
    with _engine(tmp_path, station, cell, proc) as engine:
        assert engine.execute() == "FINISHED"
        first = engine.store.samples(engine.run_id)[0]
    assert first.ok and first.solved.quality.attempts == 3
    assert first.t_committed - first.t_start >= 0.3 + 0.6  # waited 0.3 s, then 0.6 s, before the retries


def _datum_rows(results):
    (rows,) = results["data"].values()
    return rows


def test_a_resumed_displacement_group_reestablishes_its_datum(setup):
    tmp_path, station, cell = setup
    proc = _procedure(tmp_path, "displacement_calibration", axes="[y]", repeats=2, groups=1,
                      group_start_offsets_mm="[[0, 0, 0]]")

    def listener(event):
        if event["event"] == "progress" and event["done"] == 20:  # in the group's second repeat
            engine.request_pause("end of shift")

    with _engine(tmp_path, station, cell, proc, listener=listener, pause_timeout_s=0) as engine:
        assert engine.execute() == "PAUSED"
        run_id = engine.run_id
    # The next morning: a new process, and the interferometer has lost its count (re-aimed, power-cycled).
    fresh = FakeCell(seed=8, truth_log=tmp_path / "truth.jsonl")
    with _engine(tmp_path, None, fresh, run_id=run_id) as engine:
        assert engine.execute() == "FINISHED"
        samples = engine.store.samples(run_id)
        events = engine.store.events(run_id)
        results = engine.store.get_run(run_id)["results"]
    datums = [e["message"] for e in events if e["kind"] == "datum"]
    assert len(datums) == 1 and "no datum in this session" in datums[0] and "disp/y/g0/r1/p05" in datums[0]
    assert [s.reference.readings["datum_reestablished"] for s in samples] == [False] * 20 + [True] * 10
    assert len({s.reference.readings["datum_set_at"] for s in samples}) == 2
    # The analysis joins the two datums: the offset the robot's repeatability put between them is
    # estimated from the points measured under both, so the fitted references follow the truth.
    rows = _datum_rows(results)
    assert {row["group"] for row in rows} == {0} and {row["datum"] for row in rows} == {0, 1}
    first = np.mean([r["reference"] - r["true"] for r in rows if r["datum"] == 0])
    second = np.mean([r["reference"] - r["true"] for r in rows if r["datum"] == 1])
    raw = np.mean([r["reference_raw"] - r["true"] for r in rows if r["datum"] == 1])
    assert abs(second - first) < 0.5e-6  # joined to a fraction of a µm (the fake's noise is 0.3 µm)
    assert abs(raw - first) > 1e-6  # ... while the raw readings of the second datum were off by µm


def test_a_datum_lost_mid_group_is_reestablished_and_the_run_goes_on(setup):
    tmp_path, station, cell = setup
    cell.lose_datum_on_reads = {7}
    proc = _procedure(tmp_path, "displacement_calibration", axes="[z]", repeats=2, groups=1,
                      group_start_offsets_mm="[[0, 0, 0]]", retry_backoff_s=0)
    with _engine(tmp_path, station, cell, proc) as engine:
        assert engine.execute() == "FINISHED"
        samples = engine.store.samples(engine.run_id)
        events = engine.store.events(engine.run_id)
    assert [e["kind"] for e in events if e["kind"].startswith("datum")] == ["datum_lost", "datum"]
    assert [s.reference.readings["datum_reestablished"] for s in samples] == [False] * 6 + [True] * 24
    for s in samples:  # every reference still follows the commanded position, within the robot's repeatability
        assert s.reference.value == pytest.approx(s.meta["nominal"], abs=40e-6)


# --------------------------------------------------------------------------- signals and states
def _signals(tmp_path, station, cell, proc, presses, pause_handler):
    """Run with the CLI's signal handling; ``presses[done]`` are the signals raised when ``done``
    samples are committed (the handlers run in this thread, as in the CLI)."""
    import signal

    from procedures.cli import signals_control

    def listener(event):
        if event["event"] == "progress":
            for sig in presses.get(event["done"], ()):
                signal.raise_signal(sig)

    with _engine(tmp_path, station, cell, proc, listener=listener, pause_handler=pause_handler) as engine:
        with signals_control(engine):
            state = engine.execute()
        return state, engine.store.get_run(engine.run_id), _states(engine.store, engine.run_id)


def test_ctrl_c_pauses_again_after_any_number_of_resumes(setup):
    import signal

    tmp_path, station, cell = setup
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2)
    presses = {2: [signal.SIGINT], 6: [signal.SIGINT], 9: [signal.SIGINT]}
    state, run, states = _signals(tmp_path, station, cell, proc, presses, lambda engine: "resume")
    assert state == "FINISHED"
    assert states == ["RUNNING"] + ["PAUSED", "RUNNING"] * 3 + ["FINISHED"]


def test_two_ctrl_c_after_a_resume_abort_and_stop_the_robot(setup):
    import signal

    tmp_path, station, cell = setup
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2)
    presses = {2: [signal.SIGINT], 5: [signal.SIGINT, signal.SIGINT]}
    state, run, states = _signals(tmp_path, station, cell, proc, presses, lambda engine: "resume")
    assert state == "ABORTED" and run["reason"].startswith("aborted by a second Ctrl-C")
    assert states == ["RUNNING", "PAUSED", "RUNNING", "ABORTED"]
    assert cell.robot.stops >= 1


@pytest.mark.parametrize("name", ["SIGTERM", "SIGHUP"])
def test_sigterm_and_sighup_abort_like_a_second_ctrl_c(setup, name):
    import signal

    tmp_path, station, cell = setup
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2)
    state, run, states = _signals(tmp_path, station, cell, proc, {4: [getattr(signal, name)]},
                                  lambda engine: "resume")
    assert state == "ABORTED" and run["reason"].startswith(f"aborted by {name}")
    assert run["exit_status"] == "abort" and states == ["RUNNING", "ABORTED"]
    assert cell.robot.stops >= 1 and cell.table.stops >= 0


def test_a_detached_pause_returns_at_once(setup):
    from procedures.cli import detach_at_once

    tmp_path, station, cell = setup
    cell.protective_stop_on_moves = {3}
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2)
    # With --jsonl a protective stop must end the command (exit 3), not wait the hour of pause_timeout_s.
    with _engine(tmp_path, station, cell, proc, pause_handler=detach_at_once, pause_timeout_s=3600) as engine:
        assert engine.execute() == "PAUSED"
        assert "ProtectiveStop" in engine.store.get_run(engine.run_id)["reason"]


def test_a_hanging_hook_does_not_hold_up_the_run_and_every_event_is_accounted_for(tmp_path):
    station = write_station(tmp_path / "station.yaml")
    proc = tmp_path / "iso.yaml"
    proc.write_text("procedure: iso9283_repeatability\n"
                    "parameters: {cycles: 2, settle_time_s: 0, frames_per_pose: 1}\n"
                    "hooks:\n  - call: tests.fakes:hanging_hook\n    timeout_s: 1\n")
    cell = FakeCell(seed=4)
    start = time.monotonic()
    with _engine(tmp_path, station, cell, proc) as engine:
        assert engine.execute() == "FINISHED"
        events = engine.store.events(engine.run_id)
        samples = engine.store.samples(engine.run_id)
    elapsed = time.monotonic() - start
    # In the step loop, 17 events × 1 s would take 17 s; off it, the run waits at most one deadline at its end.
    assert elapsed < 10, elapsed
    assert len(samples) == 15
    failed = [e["message"] for e in events if e["kind"] == "hook_failed"]
    assert len(failed) == 17  # run_started, 15 × point_measured, run_finished: each delivered or logged
    assert any("did not return within 1.0 s" in m for m in failed)


def test_a_resume_that_cannot_start_leaves_the_run_as_it_was(setup):
    """A paused run resumed while its robot is unreachable once became FAILED for good ('dry run failed:
    robot: not reachable'); it stays PAUSED, the reason logged, and resumes later to the end."""
    from procedures.station import ResumeRefused

    tmp_path, station, cell = setup
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2)

    def listener(event):
        if event["event"] == "progress" and event["done"] == 4:
            engine.request_pause("end of shift")

    with _engine(tmp_path, station, cell, proc, listener=listener, pause_timeout_s=0.1) as engine:
        assert engine.execute() == "PAUSED"
        run_id = engine.run_id
    cell.robot.unreachable = True
    with _engine(tmp_path, None, cell, run_id=run_id) as engine:
        with pytest.raises(ResumeRefused, match=r"was not resumed \(it stays PAUSED\): dry run failed"):
            engine.execute()
        run = engine.store.get_run(run_id)
        assert run["state"] == "PAUSED" and run["reason"] == "end of shift"
        assert [e["kind"] for e in engine.store.events(run_id)][-1] == "resume_refused"
    assert cell.moves == 4
    cell.robot.unreachable = False
    with _engine(tmp_path, None, cell, run_id=run_id) as engine:
        assert engine.execute() == "FINISHED"
        assert [s.step_index for s in engine.store.samples(run_id)] == list(range(15))


def test_frames_exposed_before_the_motion_ended_are_measured_again_whatever_they_show(setup):
    """A frame must be proven to show the scene after the motion ended (its exposure time against the
    motion's): a triple exposed before it (here the previous pose's, left in the cameras' buffers) fails the
    attempt even with the plausibility check off, where it would be stored as good; the pose is measured
    again and every stored sample carries the proof of its frames."""
    tmp_path, station, cell = setup
    cell.stale_after_moves = {3: 1}
    cell.old_after_moves = {3: 1}
    proc = _procedure(tmp_path, "iso9283_repeatability", cycles=2, frames_per_pose=1, plausibility_mm=0,
                      plausibility_deg=0, retry_backoff_s=0)
    with _engine(tmp_path, station, cell, proc) as engine:
        assert engine.execute() == "FINISHED"
        samples = engine.store.samples(engine.run_id)
        events = [e["message"] for e in engine.store.events(engine.run_id) if e["kind"] == "measure_failed"]
    assert len(events) == 1 and events[0].startswith(samples[2].step_key)
    assert "before the motion was done (a stale frame)" in events[0]
    p4 = [s.solved.pose[:3] for s in samples if s.label == "P4"]
    assert samples[2].ok and np.max(np.ptp(p4, axis=0)) < 1e-3  # P4's own pose, not P5's
    for sample in samples:
        proof = sample.solved.quality.exposure
        assert proof is not None and len(proof.frames) == 3 and proof.motion_ended is not None
        assert all(f.evidence == "exposure" and f.at >= proof.motion_ended for f in proof.frames)


class _RealFitScience(FakeScience):
    """The fakes' measurements, the instrument's own calibration fit (which refuses degenerate data)."""

    def fit_calibration(self, kind, data, provenance):
        from procedures.station import InstrumentScience
        return InstrumentScience.fit_calibration(self, kind, data, provenance)  # uses no state of its own


def test_a_calibration_whose_points_all_failed_ends_with_one_line_saying_so(setup):
    """Every attempt at the first of 5 points fails: 4 points are too few for the held-out fit, and the
    run ends with a typed one-line reason naming the lost point, not an untyped ValueError."""
    tmp_path, station, cell = setup
    proc = _procedure(tmp_path, "displacement_calibration", axes="[y]", repeats=2, groups=1, stop_mm=20,
                      group_start_offsets_mm="[[0, 0, 0]]", retry_backoff_s=0, retries_per_pose=1,
                      max_failed_samples=10)
    cell.fail_measures = 2  # the first step (y = 0 mm, repeat 0): both its attempts fail

    def listener(event):  # ... and the first step of repeat 1, which follows step 4
        if event["event"] == "progress" and event["step"] == 4:
            cell.fail_measures = 2

    with open_engine(tmp_path / "runs", procedure=proc, station=station, science=_RealFitScience(cell),
                     devices=cell.devices(), operator=cell.operator, listener=listener) as engine:
        state = engine.execute()
        run = engine.store.get_run(engine.run_id)
        events = engine.store.events(engine.run_id)
        samples = engine.store.samples(engine.run_id)
    assert [s.ok for s in samples] == [False, True, True, True, True] * 2
    assert state == "FAILED"
    reason = run["reason"]
    assert "\n" not in reason and "ValueError" not in reason and "Traceback" not in reason
    assert reason.startswith("the calibration analysis refused the data: y: leave-one-point-out needs at least 5")
    assert "every sample failed at y point 0" in reason
    assert not [e for e in events if e["kind"] == "traceback"]
