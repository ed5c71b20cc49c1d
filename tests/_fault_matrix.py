"""The fault matrix's cases and how one is run (tests/test_fault_matrix_*.py: two modules, so that two
workers share the cases, each on a cell of its own): every fault kind of every twin's fault plan,
injected mid-run through the simulated cell's control channel (``SimCell.inject_fault``; the camera
twin's laser through its own control API), into ``instrument run`` in a child process, exactly as an
operator would run it.

Each case asserts the outcome the run must have — **recovered** (the run finishes by itself),
**paused** (exit 3, left PAUSED) or **failed** (exit 1, FAILED with a typed error naming device,
operation and cause) — then resumes a run that did not finish with ``instrument resume`` to
FINISHED, and checks: every planned step has exactly one sample, none failed, and every committed
sample agrees with the twins' ground truth (pose, table angle, interferometer displacement per datum).
Faults that a driver or the engine recovers from are injected one after another into one run
(each must fire and leave the run going); faults that stop a run get a run of their own.

``FAULT_MATRIX_TABLE=path pytest tests/test_fault_matrix_*.py`` also writes the table of outcomes
(the one in docs/reliability.md): each module leaves its rows beside it (``path.<part>.json``) and
rewrites the table from every part found there, in the order of ``CASES``.
"""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from instrument import ARCSEC
from procedures.station import TruthLog
from sim_devices.cell import STATIC_ROBOT, SimCell

ROOT = Path(__file__).resolve().parents[1]
# Small procedures: each run is 10-18 poses. Retries back off as by default (1 s, then 2 s).
COMMON = "settle_time_s: 0.05, frames_per_pose: 1"
PROCEDURES = {
    "iso": f"procedure: iso9283_repeatability\nparameters: {{cycles: 2, transform_step: false, {COMMON}}}\n",
    "iso_strict": ("procedure: iso9283_repeatability\nparameters: {cycles: 2, transform_step: false, "
                   f"max_failed_samples: 0, {COMMON}}}\n"),
    "angle": ("procedure: angle_calibration\nparameters: {axes: [z], groups: 1, group_start_offsets_deg: [0.0], "
              f"repeats: 2, step_deg: 0.25, table_speed_deg_s: 20.0, {COMMON}}}\n"),
    "displacement": ("procedure: displacement_calibration\nparameters: {axes: [x], groups: 1, "
                     "group_start_offsets_mm: [[0, 0, 0]], repeats: 2, step_mm: 10, stop_mm: 40, "
                     f"interferometer_average_s: 0.05, {COMMON}}}\n"),
    # 1 mm steps: a frame of the previous point is only 1 mm off, below the 2 mm plausibility limit.
    "displacement_1mm": ("procedure: displacement_calibration\nparameters: {axes: [x], groups: 1, "
                         "group_start_offsets_mm: [[0, 0, 0]], repeats: 2, step_mm: 1, stop_mm: 5, "
                         f"interferometer_average_s: 0.05, {COMMON}}}\n"),
}
# The cell's settled changes wait at most this long for the cameras (10 s by default): the starved camera
# below takes longer, so the robot says "done" while the cameras still show the previous point.
ACK_TIMEOUT_S = 2.0
EXIT = {"FINISHED": 0, "FAILED": 1, "ABORTED": 2, "PAUSED": 3}


@dataclass
class Fault:
    device: str  # robot, rotary_table, interferometer, or cameras (the laser, through the camera twin)
    kind: str
    at: int  # injected once this many samples are committed
    params: dict[str, Any] = field(default_factory=dict)
    lasts_s: float | None = None  # cameras: the laser comes back after this long


@dataclass
class Case:
    name: str
    procedure: str
    faults: list[Fault]
    outcome: str  # recovered | paused | failed
    error_device: str | None = None  # the device the typed error must name


CASES = [
    Case("robot protective stop", "iso", [Fault("robot", "protective_stop", 3)], "paused", "robot"),
    Case("robot emergency stop", "iso", [Fault("robot", "emergency_stop", 3)], "paused", "robot"),
    Case("robot program stopped", "iso", [Fault("robot", "program_stopped", 3)], "failed", "robot"),
    Case("robot disconnect", "iso", [Fault("robot", "disconnect", 3)], "paused", "robot"),
    Case("robot stall, delay, slow", "iso", [Fault("robot", "stall", 2, {"seconds": 1.0}),
                                            Fault("robot", "delay", 4, {"seconds": 1.0}),
                                            Fault("robot", "slow", 6, {"seconds": 0.02})], "recovered"),
    Case("rotary table exception 4", "angle", [Fault("rotary_table", "exception", 3, {"code": 4})], "failed",
         "rotary_table"),
    # A fault the run can go on from once the device is back: PAUSED with the typed error, not FAILED.
    Case("rotary table drops 20 replies", "angle", [Fault("rotary_table", "drop_reply", 3, {"count": 20})], "paused",
         "rotary_table"),
    Case("rotary table transport faults", "angle", [
        Fault("rotary_table", "drop_reply", 1), Fault("rotary_table", "delay", 2, {"seconds": 0.5}),
        Fault("rotary_table", "slow", 3, {"seconds": 0.02}), Fault("rotary_table", "garbage", 4),
        Fault("rotary_table", "truncate", 5), Fault("rotary_table", "bad_crc", 6),
        Fault("rotary_table", "stall", 7, {"seconds": 1.0}), Fault("rotary_table", "disconnect", 8, {"seconds": 0.5}),
        Fault("rotary_table", "exception", 9, {"code": 6})], "recovered"),
    Case("interferometer feed faults", "displacement", [
        Fault("interferometer", "stall", 1, {"seconds": 1.0}), Fault("interferometer", "drop_reply", 2, {"frames": 5}),
        Fault("interferometer", "bad_crc", 3, {"frames": 2}), Fault("interferometer", "garbage", 4),
        Fault("interferometer", "beam_break", 5, {"seconds": 0.5}),
        Fault("interferometer", "disconnect", 7, {"seconds": 1.0})], "recovered"),
    Case("cameras laser off 2 s", "iso", [Fault("cameras", "laser_off", 3, lasts_s=2.0)], "recovered"),
    Case("cameras laser off 8 s", "iso_strict", [Fault("cameras", "laser_off", 3, lasts_s=8.0)], "failed"),
    # The camera process starved (its frames come after the acknowledgement timeout): such frames once
    # stored 1 mm steps as good samples 0.9 mm off. Every frame must prove it shows the scene after the move.
    Case("cameras starved", "displacement_1mm", [Fault("cameras", "render_delay", 3, {"seconds": 3.0, "count": 3})],
         "recovered"),
]


def cases_on(*procedures: str) -> list[Case]:
    """The cases that run one of ``procedures`` (keys of ``PROCEDURES``)."""
    return [case for case in CASES if case.procedure in procedures]


@contextmanager
def fault_matrix_cell(directory: Path) -> Iterator[SimCell]:
    """The cell the cases run on: seed 11, time scale 4, the robot at rest between moves (no dense truth)."""
    with SimCell(seed=11, directory=directory, time_scale=4.0,
                 config={"world": {"ack_timeout_s": ACK_TIMEOUT_S}, "robot": STATIC_ROBOT}) as running:
        yield running


def _committed(db: Path) -> int:
    if not db.exists():
        return 0
    with sqlite3.connect(db, timeout=10) as conn:
        try:
            return conn.execute("SELECT COUNT(*) FROM samples").fetchone()[0]
        except sqlite3.OperationalError:
            return 0


def _cli(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "procedures.cli", *args, "--jsonl"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _finish(child: subprocess.Popen, timeout: float = 180) -> tuple[int, str, str]:
    try:
        out, err = child.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        child.kill()  # our own child, by its handle
        out, err = child.communicate()
        pytest.fail(f"instrument did not end within {timeout} s; stderr: {err[-2000:]}")
    return child.returncode, out, err


def _inject(cell: SimCell, fault: Fault) -> None:
    if fault.device != "cameras":
        cell.inject_fault(fault.device, fault.kind, **fault.params)
        return
    if fault.kind == "render_delay":
        cell.forward("cameras", "render_delay", **fault.params)
        return
    cell.forward("cameras", "laser", on=False)
    timer = threading.Timer(fault.lasts_s or 0.0, lambda: cell.forward("cameras", "laser", on=True))
    timer.daemon = True
    timer.start()


def _clear(cell: SimCell) -> None:
    for device in ("robot", "rotary_table", "interferometer"):
        cell.clear_faults(device)
    cell.forward("cameras", "laser", on=True)
    cell.forward("cameras", "render_delay", seconds=0.0)


def _store(runs: Path) -> tuple[dict, list[dict], list[dict], int]:
    with sqlite3.connect(runs / "runs.sqlite") as conn:
        conn.row_factory = sqlite3.Row
        (run,) = [dict(r) for r in conn.execute("SELECT * FROM runs")]
        samples = [dict(r) for r in conn.execute("SELECT * FROM samples ORDER BY step_index")]
        events = [dict(r) for r in conn.execute("SELECT * FROM events ORDER BY rowid")]
        superseded = conn.execute("SELECT COUNT(*) FROM superseded_samples").fetchone()[0]
    for sample in samples:
        for key in ("solved", "reference", "meta"):
            sample[key] = json.loads(sample[key]) if sample[key] else None
    return run, samples, events, superseded


def _check_against_truth(procedure: str, samples: list[dict], truth: TruthLog) -> None:
    """Every committed sample against the twins' truth at its frame time."""
    offsets: dict[float, list[float]] = {}
    for sample in samples:
        state = truth.at(sample["t_measured"])
        assert state is not None, sample["step_key"]
        true = np.array(state["opr_in_m"]["t"] + state["opr_in_m"]["euler"])
        solved = np.array(sample["solved"]["pose"])
        # The raw instrument is off by tens of µm and arc-seconds; a pose from another step would be
        # 10 mm or 0.25° away.
        assert np.all(np.abs(solved[:3] - true[:3]) < 300e-6), (sample["step_key"], solved - true)
        assert np.all(np.abs(solved[3:] - true[3:]) < 300 * ARCSEC), (sample["step_key"], solved - true)
        if procedure == "angle":
            assert abs(sample["reference"]["value"] - true[5]) < 0.6 * ARCSEC, sample["step_key"]
        if procedure == "displacement":
            datum = sample["reference"]["datum_set_at"]
            offsets.setdefault(datum, []).append(sample["reference"]["value"] - true[0])
    for datum, values in offsets.items():  # within one datum the reference follows the truth
        assert np.ptp(values) < 1e-6, (datum, np.ptp(values))


def _check_datums_joined(results: dict) -> int:
    """The analysis brought every re-established datum onto its group's first one: the references it
    fitted agree with the truth up to one offset per group (the noise of the estimate: a few µm,
    against the ~10 µm the robot's repeatability puts between two datums). Returns how many datums
    were joined."""
    joined = 0
    for rows in results["data"].values():
        for group in {row["group"] for row in rows}:
            mine = [row for row in rows if row["group"] == group]
            first = [row["reference"] - row["true"] for row in mine if row.get("datum", 0) == 0]
            for datum in sorted({row.get("datum", 0) for row in mine} - {0}):
                later = [row["reference"] - row["true"] for row in mine if row["datum"] == datum]
                assert abs(np.mean(later) - np.mean(first)) < 3e-6, (group, datum, np.mean(later) - np.mean(first))
                joined += 1
    return joined


def _row(case: Case, index: int, outcome: str, detect_s: float | None, lost: int, resumed: bool) -> dict[str, Any]:
    fault = case.faults[index]
    params = ", ".join(f"{k}={v}" for k, v in fault.params.items())
    if fault.lasts_s is not None:
        params = f"{fault.lasts_s:g} s"
    return {"order": [CASES.index(case), index], "device": fault.device,
            "fault": fault.kind + (f" ({params})" if params else ""), "outcome": outcome, "detect_s": detect_s,
            "lost": lost, "resumed": resumed, "note": ""}


def write_table(part: str, rows: list[dict[str, Any]]) -> None:
    """Print this module's rows; with ``FAULT_MATRIX_TABLE``, leave them beside the table and rewrite the
    table from every module's rows found there."""
    target = os.environ.get("FAULT_MATRIX_TABLE")
    if target:
        Path(f"{target}.{part}.json").write_text(json.dumps(rows), encoding="utf-8")
        rows = [row for found in sorted(Path(target).parent.glob(Path(target).name + ".*.json"))
                for row in json.loads(found.read_text(encoding="utf-8"))]
    rows = sorted(rows, key=lambda row: row["order"])
    lines = ["| device | fault | outcome | time to outcome (s) | lost samples | resumed to FINISHED |",
             "|---|---|---|---|---|---|"]
    for row in rows:
        detect = "—" if row["detect_s"] is None else f"{row['detect_s']:.1f}"
        lines.append(f"| {row['device']} | {row['fault']} | {row['outcome']}{row['note']} | {detect} | {row['lost']} "
                     f"| {'yes' if row['resumed'] else 'not needed'} |")
    print("\n" + "\n".join(lines))
    if target:
        Path(target).write_text("\n".join(lines) + "\n", encoding="utf-8")


def run_case(cell: SimCell, tmp_path: Path, case: Case) -> list[dict[str, Any]]:
    """Run ``case`` on ``cell`` (its runs under ``tmp_path``), assert its outcome and what resume and the
    twins' truth say; returns its rows of the table."""
    _clear(cell)
    runs = tmp_path / "runs"
    procedure = tmp_path / "procedure.yaml"
    procedure.write_text(PROCEDURES[case.procedure], encoding="utf-8")
    child = _cli("run", str(procedure), "--station", str(cell.station_path), "--runs-dir", str(runs))
    injected: list[float] = []
    deadline = time.monotonic() + 120
    for fault in case.faults:
        while _committed(runs / "runs.sqlite") < fault.at and child.poll() is None:
            assert time.monotonic() < deadline, "the run made no progress"
            time.sleep(0.01)
        assert child.poll() is None, f"the run ended before fault {fault.kind} was injected: {child.stderr.read()}"
        if injected and case.faults[len(injected) - 1].kind == "slow":
            cell.clear_faults(case.faults[len(injected) - 1].device)  # "slow" lasts until cleared
        injected.append(time.time())
        _inject(cell, fault)
    code, out, err = _finish(child)
    died = -code if code < 0 else 0  # the signal that ended the process, if one did
    assert "Traceback" not in err, err[-3000:]
    run, samples, events, _ = _store(runs)
    state, reason = run["state"], run["reason"] or ""

    expected_state = {"recovered": "FINISHED", "paused": "PAUSED", "failed": "FAILED"}[case.outcome]
    assert state == expected_state, (state, reason, err[-2000:])
    assert died or code == EXIT[state], (code, err[-2000:])
    if case.error_device:  # a typed device error: "device: operation failed: cause"
        assert f"{case.error_device}: " in reason and " failed: " in reason, reason
    for fault in case.faults:  # each fault really happened
        if fault.device != "cameras":
            fired = [kind for kind, _ in cell.fired_faults(fault.device)]
            assert fault.kind in fired or fault.kind == "slow", (fault.kind, fired)

    # Time to the outcome: the state change for a run that stopped; for a recovered fault, the time
    # the step during which it happened took beyond the median step.
    durations = [s["t_committed"] - s["t_start"] for s in samples]
    median = statistics.median(durations)
    detect: list[float | None] = []
    for when in injected:
        if case.outcome != "recovered":
            change = next(e["time"] for e in events if e["kind"] == "state" and e["time"] > when
                          and not e["message"].startswith("RUNNING"))
            detect.append(change - when)
        else:
            after = [s for s in samples if s["t_committed"] > when]
            detect.append(max(0.0, after[0]["t_committed"] - after[0]["t_start"] - median) if after else None)

    resumed = state != "FINISHED"
    if resumed:
        _clear(cell)
        resume_code, out, err = _finish(_cli("resume", run["id"], "--runs-dir", str(runs)))
        assert resume_code == 0, err[-2000:]
        run, samples, events, _ = _store(runs)
        assert run["state"] == "FINISHED", run["reason"]

    total = run["total_steps"]
    assert [s["step_index"] for s in samples] == list(range(total))  # every step once: none lost or doubled
    lost = sum(1 for s in samples if not s["ok"])
    assert lost == 0, [s["error"] for s in samples if not s["ok"]]
    _check_against_truth(case.procedure.split("_")[0], samples, TruthLog.read(cell.truth_path))
    if case.procedure.startswith("displacement"):
        reestablished = [e for e in events if e["kind"] == "datum"]
        assert _check_datums_joined(json.loads(run["results"])) == len({e["message"] for e in reestablished})
    # ur_rtde runs in a worker process (drivers/robot): a client that crashes must not take the run with it.
    assert not died, f"outcome recorded ({state}: {reason}), but the run process died by {signal.Signals(died).name}"
    return [_row(case, index, case.outcome, seconds, lost, resumed) for index, seconds in enumerate(detect)]
