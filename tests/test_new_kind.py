"""A new procedure kind is one module: the engine, the loader, the CLI and the report run it without
knowing it. The kind here is defined in this file, with a result shape of its own and the report's
section for it, both registered for the test only."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np
import pytest
from pydantic import Field

import procedures.kinds as kinds
import procedures.report as report
from procedures.cli import main
from procedures.engine import json_schemas, open_engine
from procedures.kinds import (
    Analysis,
    AnalysisContext,
    DeviceRole,
    MotionParameters,
    OprOnRobot,
    ProcedureBase,
    Reading,
    Step,
    StepContext,
)
from procedures.station import StationFile, Vec3, translated_in_frame
from procedures.store import RunState, Sample
from tests.fakes import FakeCell, FakeScience, write_station


# ------------------------------------------------------------------ the whole new kind: one "module"
class StationaryParameters(MotionParameters):
    visits: int = Field(8, ge=2, description="times the robot comes back to the point")
    position_m: Vec3 = Field(default_factory=lambda: [0.01, 0.02, 0.03], description="the point in M, metres")


class StationaryRepeat(ProcedureBase):
    procedure: Literal["stationary_repeat"]
    parameters: StationaryParameters = Field(default_factory=StationaryParameters)


class StationaryRepeatKind:
    """Come back to one point, alternating with M's origin; report the spread of the attained positions."""

    name = "stationary_repeat"
    parameters = StationaryParameters
    file_model = StationaryRepeat

    def plan(self, params: StationaryParameters, station: StationFile) -> list[Step]:
        steps: list[Step] = []
        for visit in range(params.visits):
            for label, point in (("away", [0.0, 0.0, 0.0]), ("point", params.position_m)):
                steps.append(Step(index=len(steps), key=f"stationary/v{visit:02d}/{label}", phase=label,
                                  setup=OprOnRobot(), label=label,
                                  tcp_pose=translated_in_frame(station.frames.reference_tcp_pose, point).tolist()))
        return steps

    def devices(self, params: StationaryParameters) -> tuple[DeviceRole, ...]:
        return ("robot",)

    def applies_compensation(self, params: StationaryParameters) -> bool:
        return False

    def move(self, step: Step, params: StationaryParameters, ctx: StepContext) -> None:
        ctx.move_robot(step.robot_target())

    def measure(self, step: Step, params: StationaryParameters, ctx: StepContext) -> Reading:
        ctx.settle()
        return Reading(pose=ctx.measure_pose(step))

    def analyse(self, samples: Sequence[Sample], params: StationaryParameters, ctx: AnalysisContext) -> Analysis:
        at_point = [s for s in samples if s.phase == "point" and s.ok and s.solved]
        positions = np.array([s.solved.pose[:3] for s in at_point if s.solved])
        results: dict[str, Any] = {"kind": "stationary", "n": len(positions),
                                   "spread_m": positions.std(axis=0, ddof=1).tolist()}
        if ctx.truth is not None:
            true = [ctx.truth.at(s.t_measured) for s in at_point if s.t_measured is not None]
            results["true_spread_m"] = np.std([t["opr_in_m"]["t"] for t in true if t], axis=0, ddof=1).tolist()
        return Analysis(results=results)

    result_shape = "stationary"
    iso_test_conditions = False
    history_figures = ()

    def title(self, parameters: Mapping[str, Any], results: Mapping[str, Any] | None) -> str:
        return f"Stationary repeat — {parameters['visits']} visits"


# ... and, in the report, the section of its results' shape
STATIONARY_SECTION = report.ResultSection(
    html=lambda results: f"<h2>Stationary repeat</h2><p>{results['n']} visits</p>",
    show_lines=lambda results: [f"visits     {results['n']}"])


# ------------------------------------------------------------------------------------------ tests
@pytest.fixture
def registered():
    kinds.register(StationaryRepeatKind())
    report.register_section("stationary", STATIONARY_SECTION)
    yield
    report.unregister_section("stationary")
    kinds.unregister("stationary_repeat")


def test_the_engine_runs_a_kind_it_does_not_know(registered, tmp_path, capsys):
    truth = tmp_path / "truth.jsonl"
    station = write_station(tmp_path / "station.yaml", truth_log=str(truth))
    procedure = tmp_path / "stationary.yaml"
    procedure.write_text("procedure: stationary_repeat\n"
                         "parameters: {visits: 12, settle_time_s: 0, frames_per_pose: 1}\n")
    assert main(["validate", str(procedure)]) == 0
    assert "OK (stationary_repeat)" in capsys.readouterr().out

    cell = FakeCell(seed=8, truth_log=truth, robot_sigma=20e-6)
    with open_engine(tmp_path / "runs", procedure=procedure, station=station, science=FakeScience(cell),
                     devices=cell.devices(), operator=cell.operator) as engine:
        assert engine.execute() == RunState.FINISHED
        run = engine.store.get_run(engine.run_id)
    results = run["results"]
    assert results["n"] == 12 and cell.moves == 24
    # The fake instrument's noise (0.3 µm) and error slope (≤ 2.5e-3) hardly change a 20 µm spread.
    np.testing.assert_allclose(results["spread_m"], results["true_spread_m"], rtol=0.05)

    assert main(["show", run["id"], "--runs-dir", str(tmp_path / "runs")]) == 0
    assert "visits     12" in capsys.readouterr().out
    assert main(["report", run["id"], "--runs-dir", str(tmp_path / "runs")]) == 0
    html = open(capsys.readouterr().out.strip(), encoding="utf-8").read()
    assert "<h2>Stationary repeat</h2><p>12 visits</p>" in html
    assert "<h1>Stationary repeat — 12 visits</h1>" in html  # the title the kind words from its parameters


def test_its_schema_and_errors_come_with_it(registered, tmp_path, capsys):
    schema = json_schemas()["stationary_repeat"]
    assert schema["properties"]["procedure"]["const"] == "stationary_repeat"
    assert "visits" in json.dumps(schema)
    bad = tmp_path / "bad.yaml"
    bad.write_text("procedure: stationary_repeat\nparameters:\n  visits: 1\n")
    assert main(["validate", str(bad)]) == 1
    assert f"{bad}:3: parameters.visits: input should be greater than or equal to 2" in capsys.readouterr().err


def test_an_unregistered_kind_is_one_clear_line(tmp_path, capsys):
    path = tmp_path / "stationary.yaml"
    path.write_text("procedure: stationary_repeat\n")
    assert main(["validate", str(path)]) == 1
    assert capsys.readouterr().err.strip().startswith(f"{path}:1: procedure: expected one of displacement_calibration")
