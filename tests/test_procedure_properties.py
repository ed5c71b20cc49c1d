"""Properties of procedure files and plans, over generated inputs (hypothesis, derandomized).

- Any procedure file either validates or is refused with one clear line per problem
  (``FILE:LINE: field: what``), never a traceback.
- A plan is a pure function of the parameters (a resumed run rebuilds the same steps), sized as
  the parameters say, and asks the operator for a new set-up once per axis.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
import yaml
from hypothesis import find, given, settings
from hypothesis import strategies as st

from procedures.engine import load_procedure
from procedures.kinds import KINDS, ProcedureBase
from procedures.kinds.calibration import AngleParameters, DisplacementParameters
from procedures.kinds.iso import IsoParameters
from procedures.station import ConfigError, StationFile, tcp_in_m
from tests.fakes import station_dict

# Reproducible: the same examples on every run, no example database between runs.
SETTINGS = settings(derandomize=True, database=None, deadline=None, max_examples=300)
PLAN_SETTINGS = settings(SETTINGS, max_examples=100)  # a plan has up to hundreds of steps
ONE_PROBLEM = re.compile(r"^gen\.yaml:\d+: \S[^\n]*$")
STATION = StationFile.model_validate(station_dict())

scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**9, 10**9), st.floats(), st.text(max_size=12))
values = st.recursive(
    scalars, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=10,
)
known_keys = sorted({name for kind in KINDS.values() for name in kind.parameters.model_fields})
# Values of the kinds the parameters take, so that many generated files are close to valid ...
plausible = st.one_of(st.integers(0, 40), st.floats(0, 80), st.booleans(),
                      st.sampled_from(["never", "failed", "always"]),
                      st.lists(st.sampled_from(["x", "y", "z"]), min_size=1, max_size=3),
                      st.lists(st.floats(-1, 1), min_size=3, max_size=3))
near_valid = st.fixed_dictionaries({"procedure": st.sampled_from(sorted(KINDS))}, optional={
    "parameters": st.dictionaries(st.sampled_from(known_keys), plausible, max_size=4),
    "name": st.text(max_size=20),
})
# ... and wild ones: any keys, any values, any types.
parameters = st.dictionaries(st.sampled_from(known_keys) | st.text(max_size=10), values, max_size=6)
hook = st.dictionaries(st.sampled_from(["events", "call", "shell", "http", "timeout_s", "on"]) | st.text(max_size=6),
                       values, max_size=3)
wild = st.fixed_dictionaries({}, optional={
    "procedure": st.sampled_from(sorted(KINDS)) | values,
    "parameters": parameters | values,
    "name": values,
    "description": values,
    "hooks": st.lists(hook, max_size=2) | values,
    "extra": values,
}) | values
documents = near_valid | wild


def _accepted(document) -> bool:
    try:
        load_procedure("gen.yaml", text=yaml.safe_dump(document, allow_unicode=True))
    except ConfigError:
        return False
    return True


def _judge(text: str) -> None:
    try:
        procedure = load_procedure("gen.yaml", text=text)
    except ConfigError as exc:
        assert exc.problems, "refused without a reason"
        for problem in exc.problems:
            assert ONE_PROBLEM.match(problem), problem
        return
    assert isinstance(procedure, ProcedureBase) and procedure.procedure in KINDS


@SETTINGS
@given(documents)
def test_any_procedure_mapping_validates_or_gives_one_line_per_problem(document):
    _judge(yaml.safe_dump(document, allow_unicode=True))


@SETTINGS
@given(st.text(max_size=200))
def test_any_text_validates_or_gives_one_line_per_problem(text):
    _judge(text)


def test_the_generated_files_are_both_accepted_and_refused():
    """The property above means something only if the generator reaches both outcomes."""
    search = settings(derandomize=True, database=None, deadline=None)
    valid = find(documents, lambda d: _accepted(d) and bool(d.get("parameters")), settings=search)
    invalid = find(near_valid, lambda d: not _accepted(d), settings=search)
    assert valid["procedure"] in KINDS and invalid["procedure"] in KINDS


axes = st.lists(st.sampled_from(["x", "y", "z"]), min_size=1, max_size=3, unique=True)


@st.composite
def displacement_parameters(draw):
    groups = draw(st.integers(1, 3))
    start = draw(st.floats(-20, 20))
    length = draw(st.floats(8, 70))  # at least 5 points per line: a step of at most a quarter of the line
    return DisplacementParameters(
        axes=draw(axes), start_mm=start, stop_mm=start + length, step_mm=draw(st.floats(length / 20, length / 4)),
        repeats=draw(st.integers(2, 3)), groups=groups,
        group_start_offsets_mm=draw(st.lists(st.lists(st.floats(-1, 1), min_size=3, max_size=3),
                                             min_size=groups, max_size=groups)))


@st.composite
def angle_parameters(draw):
    groups = draw(st.integers(1, 3))
    start = draw(st.floats(-2, 2))
    length = draw(st.floats(0.2, 2))
    return AngleParameters(
        axes=draw(axes), start_deg=start, stop_deg=start + length, step_deg=draw(st.floats(length / 20, length / 4)),
        repeats=draw(st.integers(2, 3)), groups=groups,
        group_start_offsets_deg=draw(st.lists(st.floats(-0.2, 0.2), min_size=groups, max_size=groups)))


def _check_plan(kind_name, params, points_per_line):
    kind = KINDS[kind_name]
    plan = kind.plan(params, STATION)
    assert plan == kind.plan(params, STATION)  # what a resumed run rebuilds
    assert [s.index for s in plan] == list(range(len(plan)))
    assert len({s.key for s in plan}) == len(plan)
    assert len(plan) == len(params.axes) * params.groups * params.repeats * points_per_line
    changes = [s.setup for i, s in enumerate(plan) if i == 0 or s.setup != plan[i - 1].setup]
    assert [setup.axis for setup in changes] == params.axes  # one set-up per axis, in order
    return plan


@PLAN_SETTINGS
@given(displacement_parameters())
def test_displacement_plan_moves_along_one_axis_of_m_per_line(params):
    points = int(np.floor((params.stop_mm - params.start_mm) / params.step_mm + 1e-9)) + 1
    plan = _check_plan("displacement_calibration", params, points)
    for step in plan:
        k = "xyz".index(step.meta["axis"])
        position = tcp_in_m(STATION.frames.reference_tcp_pose, step.robot_target())[:3, 3]
        offset = np.asarray(params.group_start_offsets_mm[step.meta["group"]]) * 1e-3
        expected = offset.copy()
        expected[k] = step.meta["nominal"]
        np.testing.assert_allclose(position, expected, atol=1e-12)
        assert step.meta["zero_interferometer"] == (step.meta["repeat"] == 0 and step.meta["point"] == 0)


@PLAN_SETTINGS
@given(angle_parameters())
def test_angle_plan_turns_the_table_only(params):
    points = int(np.floor((params.stop_deg - params.start_deg) / params.step_deg + 1e-9)) + 1
    plan = _check_plan("angle_calibration", params, points)
    for step in plan:
        assert step.tcp_pose is None
        offset = params.group_start_offsets_deg[step.meta["group"]]
        expected = params.start_deg + step.meta["point"] * params.step_deg + offset
        assert np.degrees(step.table_target()) == pytest.approx(expected, abs=1e-9)


@PLAN_SETTINGS
@given(st.integers(2, 40), st.booleans())
def test_iso_plan_visits_the_cube_in_the_papers_order(cycles, transform_step):
    params = IsoParameters(cycles=cycles, transform_step=transform_step)
    plan = KINDS["iso9283_repeatability"].plan(params, STATION)
    assert len(plan) == 5 * (cycles + transform_step)
    assert [s.label for s in plan] == ["P1", "P5", "P4", "P3", "P2"] * (cycles + transform_step)
    assert [s.phase for s in plan[:5]] == ["transform" if transform_step else "iso"] * 5
    assert len({str(s.setup) for s in plan}) == 1  # the OPR never leaves the robot
