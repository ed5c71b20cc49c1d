"""The kinds that measure while the robot moves, end to end on the simulated cell (real twins, real
ur_rtde and pypylon's emulator, through the engine), against the twins' truth: the robot twin's dense
trajectory at the stream's own instants (and, for stabilisation, at 1 kHz).

The cell has ideal optics and exact mounts (as ``benchmarks/dynamic_truth.py``): the instrument's
static errors — which a calibration record removes and these runs do not have — would otherwise add
tens of µm of slowly varying error to the path figures. The robot carries 5 kg (its rated payload)
so that the arrival rings. A kill -9 of a dynamic run is tested on the fake cell
(``test_dynamic_procedures.py``, real SQLite, a child process), and the PostgreSQL round trip there too.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from procedures.engine import open_engine
from procedures.store import RunState
from sim_devices.camera import IDEAL_OPTICS
from sim_devices.cell import SimCell
from sim_devices.trajectory import TrajectoryLog
from sim_devices.world import EXACT_MOUNTS

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]

RATE = 150.0  # Hz: 10 Hz rings sampled 15 times a cycle (the full 1040-row frame reads out in 5 ms)


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    directory = tmp_path_factory.mktemp("dynamic-cell")
    with SimCell(seed=2, directory=directory, time_scale=1.0,
                 config={"world": EXACT_MOUNTS, "optics": IDEAL_OPTICS}) as running:
        yield running


def _ms(seconds: float | None) -> str:
    return "never" if seconds is None else f"{seconds * 1e3:.2f}"


def _procedure(tmp_path: Path, kind: str, **parameters) -> Path:
    path = tmp_path / f"{kind}.yaml"
    path.write_text(yaml.safe_dump({"procedure": kind, "parameters": {
        "cycles": 2, "rate_hz": RATE, "payload_mass_kg": 5.0, "payload_cog_m": [0.0, 0.0, 0.05],
        "rest_s": 0.4, **parameters}}), encoding="utf-8")
    return path


def _robot_stalls(cell: SimCell) -> int:
    """Times the host held the robot twin's cycle back by 50 ms or more (the twin counts them)."""
    return int(cell.forward("robot", "state")["stalls"])


def _done_delays(cell: SimCell) -> list[tuple[float, float]]:
    """Per move of the cell: (its done signal, s of controller time, how long after its encoders settled
    the done came). The twin holds done until every other twin shows the settled pose (so that no grab
    after done is stale); a loaded host makes that late, where a real controller signals at once."""
    log = TrajectoryLog(cell.truth_path.parent / "trajectories")
    return [(r.meta["done_timestamp"], r.meta["done_timestamp"] - r.meta["end_timestamp"])
            for r in log.records() if "done_timestamp" in r.meta and "end_timestamp" in r.meta]


def _signalled_at_once(cell: SimCell, moves: list[dict]) -> list[dict]:
    """The measured arrivals whose done signal came within 50 ms of their encoders settling."""
    delays = _done_delays(cell)
    # A move the analysis could not measure has no t_signal (r4 on a loaded VM: KeyError): never prompt.
    return [m for m in moves if m.get("t_signal") is not None
            and any(abs(done - m["t_signal"]) < 0.01 and delay < 0.05 for done, delay in delays)]


def _all_measured(run: dict) -> bool:
    """Every move has its figures. A loaded host can make one unmeasurable (its done signal outside the
    streamed poses, or too few poses): the analysis says why in the move's ``error``, which is printed."""
    errors = [f"{m['key']}: {m['error']}" for m in run["results"]["moves"] if "error" in m]
    if errors:
        print("moves not measured:", "; ".join(errors))
    return not errors


def _run_in_real_time(cell: SimCell, tmp_path: Path, procedure: Path, usable=lambda run: True,
                      tries: int = 3) -> dict:
    """``_run``, repeated when the host held the robot twin's cycle back by 50 ms or more during the run
    (the twin counts it: the cameras saw the arm frozen while its physics went on, which no real cell
    shows), or when ``usable(run)`` says the run cannot show what the test checks. Any other failure
    fails at once; three unusable tries in a row fail too."""
    for attempt in range(1, tries + 1):
        before = _robot_stalls(cell)
        run = _run(tmp_path / f"try-{attempt}", procedure, cell.station_path)
        stalls = _robot_stalls(cell) - before
        if stalls == 0 and usable(run):
            return run
        print(f"try {attempt}: the host held the robot twin back ({stalls} stalls of 50 ms or more, or every "
              f"done signal late); measuring again")
    raise AssertionError(f"the host held the robot twin back in each of {tries} runs")


def _run(tmp_path: Path, procedure: Path, station: Path) -> dict:
    with open_engine(tmp_path / "runs", procedure=procedure, station=station) as engine:
        state = engine.execute()
        run = engine.store.get_run(engine.run_id)
        samples = engine.store.samples(engine.run_id)
        streams = engine.store.streams(engine.run_id)
    assert state == RunState.FINISHED, run["reason"]
    assert all(s.ok for s in samples), [s.error for s in samples if not s.ok]
    assert sorted(streams) == [s.step_index for s in samples if s.phase != "transform"]
    return run


def test_stabilisation_against_the_twins_truth(cell, tmp_path):
    run = _run_in_real_time(cell, tmp_path, _procedure(tmp_path, "iso9283_stabilisation", speeds_percent=[100],
                                                       band_um=10.0, window_s=0.4),
                            usable=lambda run: _all_measured(run)
                            and bool(_signalled_at_once(cell, run["results"]["moves"])))
    results = run["results"]
    assert results["simulated"] and len(results["moves"]) == 2
    period = 1.0 / RATE
    prompt = _signalled_at_once(cell, results["moves"])
    # A real ring-down: the 5 kg arrival at 1 m/s overshoots by µm and takes time to enter 10 µm. Judged on
    # the dense (1 kHz) truth: at the stream's 150 Hz instants, which fall wherever the host's timing puts
    # them, one arrival may show little of its peak, and two arrivals in a row may both. Only where the
    # done signal came as the encoders settled: a done held back by a loaded host comes after the ring-down.
    assert any(m["true"]["dense"]["overshoot"] > 3e-6 and m["true"]["dense"]["stabilisation_time"] > period
               for m in prompt)
    for move in results["moves"]:
        true = move["true"]
        print(f"{move['key']}: t_s {_ms(move['stabilisation_time'])} ms (true {_ms(true['stabilisation_time'])}, "
              f"dense {_ms(true['dense']['stabilisation_time'])}), overshoot {move['overshoot'] * 1e6:.2f} µm "
              f"(true {true['overshoot'] * 1e6:.2f}, dense {true['dense']['overshoot'] * 1e6:.2f}), "
              f"{move['poses']} poses, {move['dropped']} dropped")
        assert abs(move["stabilisation_time"] - true["stabilisation_time"]) <= period
        # within 2 µm, or within the expanded (k = 2) uncertainty the instrument states for it when that is
        # wider (a loaded host jitters the cameras' and the robot's clocks, and the uncertainty says so)
        assert abs(move["overshoot"] - true["overshoot"]) <= max(2e-6, 2 * move["u_overshoot"])
        # The stream sees the entry into the band at its first instant after it: up to one period later,
        # and the interval between two instants stretches by the host's jitter (measured 6.76 ms against a
        # 6.67 ms period in a loaded run): 1 ms is allowed for that.
        assert abs(move["stabilisation_time"] - true["dense"]["stabilisation_time"]) <= period + 1e-3
        # The 1 kHz truth peaks higher than any 150 Hz sampling of it can show (measured here: 9.6 µm dense
        # vs 6.4 µm at the stream's instants): the overshoot is judged at the stream's own instants.
        assert true["dense"]["overshoot"] >= true["overshoot"] - 0.1e-6
        assert move["dropped"] == 0 and move["u_overshoot"] < 5e-6


def test_path_accuracy_against_the_twins_truth(cell, tmp_path):
    run = _run_in_real_time(cell, tmp_path, _procedure(tmp_path, "iso9283_path", speeds_percent=[50], hold_s=0.1,
                                                       rate_hz=50.0, circle_radius_mm=10.0,
                                                       settle_time_s=0.2, frames_per_pose=1))
    setting = run["results"]["settings"][0]
    for part in ("leg_1", "leg_2", "circle"):
        figures = setting[part]
        print(f"{part}: AT_p {figures['at_p'] * 1e6:.2f} µm (true {figures['true']['at_p'] * 1e6:.2f}, "
              f"U {(figures['u_at_p'] or 0.0) * 1e6:.2f}), "
              f"RT_p {figures['rt_p'] * 1e6:.2f} µm (true {figures['true']['rt_p'] * 1e6:.2f})")
        # within 2.5 µm (measured 2.36 µm once on a loaded host, where the cameras' and the robot's clocks
        # are paired from jittered stamps), or within the expanded uncertainty the run states for AT_p when
        # that is wider (2.71 µm off was seen once in a loaded make test)
        assert abs(figures["at_p"] - figures["true"]["at_p"]) <= max(2.5e-6, figures["u_at_p"] or 0.0)
    corner = setting["corner"]
    print(f"corner: CR {corner['cr'] * 1e6:.2f} µm (true {corner['true']['cr'] * 1e6:.2f}), "
          f"CO {corner['co'] * 1e6:.2f} µm (true {corner['true']['co'] * 1e6:.2f})")
    # CR (no target) is one sample's distance, the closest: the vision's noise (σ ≈ 1–2 µm) enters it whole.
    assert abs(corner["cr"] - corner["true"]["cr"]) <= 5e-6
    velocity = setting["velocity"]
    assert abs(velocity["av"] - velocity["true"]["av"]) < 0.005
