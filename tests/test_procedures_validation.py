"""Station and procedure files: the shipped ones validate; each bad one names file, line and field."""

import json
import textwrap

import pytest
import yaml

from procedures.engine import SCHEMA_DIR, json_schemas, load_procedure, load_station
from procedures.station import ConfigError
from tests.fakes import station_dict


@pytest.mark.parametrize("name", ["displacement_calibration", "angle_calibration", "iso9283_repeatability"])
def test_shipped_procedures_validate(name):
    from procedures.engine import resolve_procedure_path

    proc = load_procedure(resolve_procedure_path(name))
    assert proc.procedure == name


def test_paper_defaults():
    proc = load_procedure("p.yaml", text="procedure: displacement_calibration\n")
    p = proc.parameters
    assert (p.start_mm, p.stop_mm, p.step_mm, p.repeats, p.groups) == (0, 70, 5, 3, 3)
    iso = load_procedure("i.yaml", text="procedure: iso9283_repeatability\n").parameters
    assert iso.cycles == 30 and iso.cube_center_m == [0.035, 0.035, 0.035]


def _problems(text, name="bad.yaml"):
    with pytest.raises(ConfigError) as info:
        load_procedure(name, text=textwrap.dedent(text))
    return info.value.problems


BAD_PROCEDURES = [
    (
        """\
     procedure: iso9283_repeatability
     parameters:
       cycles: 1
     """,
        "bad.yaml:3: parameters.cycles: input should be greater than or equal to 2",
    ),
    (
        """\
     procedure: iso9283_repeatability
     parameters:
       cube_edge_m: 0.07
       cycle: 30
     """,
        "bad.yaml:4: parameters.cycle: unknown field; expected one of",
    ),
    (
        """\
     procedure: iso9283_repeatability
     parameters:
       cube_center_m: [0.035, 0.035]
     """,
        "bad.yaml:3: parameters.cube_center_m: list should have at least 3 items",
    ),
    (
        """\
     procedure: displacement_calibration
     parameters:
       step_mm: five
     """,
        "bad.yaml:3: parameters.step_mm: input should be a valid number",
    ),
    (
        """\
     procedure: displacement_calibration
     parameters:
       groups: 2
     """,
        "bad.yaml:3: parameters.groups: groups is 2 but group_start_offsets_mm has 3 entries",
    ),
    (
        """\
     name: no kind
     parameters: {}
     """,
        "bad.yaml:1: procedure: expected one of displacement_calibration, angle_calibration, "
        "iso9283_repeatability, iso9283_stabilisation, iso9283_path (missing)",
    ),
    (
        """\
     # comment
     procedure: iso9283
     """,
        "bad.yaml:2: procedure: expected one of",
    ),
    (
        """\
     procedure: angle_calibration
     parameters:
       axes: [x, w]
     """,
        "bad.yaml:3: parameters.axes[1]: input should be 'x', 'y' or 'z'",
    ),
    (
        """\
     procedure: angle_calibration
     hooks:
       - shell: "echo hi"
         http: "http://127.0.0.1:9/x"
     """,
        "bad.yaml:3: hooks[0]: a hook needs exactly one of call, entry_point, shell, http",
    ),
    (
        """\
     procedure: angle_calibration
     hooks:
       - http: "http://example.com/hook"
     """,
        "bad.yaml:3: hooks[0].http: hooks post to loopback addresses only",
    ),
    (
        """\
     procedure: angle_calibration
     parameters: {start_deg: 1, stop_deg: [
     """,
        "bad.yaml:3: YAML syntax",
    ),
]


@pytest.mark.parametrize("text, expected", BAD_PROCEDURES)
def test_bad_procedure_names_file_line_field(text, expected):
    problems = _problems(text)
    assert any(p.startswith(expected) for p in problems), problems


def test_every_problem_is_reported():
    problems = _problems("""\
        procedure: iso9283_repeatability
        parameters:
          cycles: 0
          speed_percent: 150
          frames_per_pose: 0
        """)
    assert [p.split(":")[1] for p in problems] == ["3", "4", "5"]


def _station_problems(tmp_path, data):
    path = tmp_path / "station.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError) as info:
        load_station(path, check_geometry=False)
    lines = path.read_text().splitlines()
    return info.value.problems, lines


def test_station_missing_camera(tmp_path):
    data = station_dict()
    del data["devices"]["cameras"]["z"]
    problems, lines = _station_problems(tmp_path, data)
    assert len(problems) == 1
    where, field, message = problems[0].split(": ", 2)
    line = int(where.rsplit(":", 1)[1])
    assert field == "devices.cameras.z" and message == "required field is missing"
    assert lines[line - 1].strip() == "cameras:"


def test_station_envelope_inverted(tmp_path):
    data = station_dict()
    data["envelope"]["box_min"], data["envelope"]["box_max"] = data["envelope"]["box_max"], data["envelope"]["box_min"]
    problems, lines = _station_problems(tmp_path, data)
    assert "envelope.box_min: box_min must be below box_max" in problems[0]
    assert lines[int(problems[0].split(":")[1]) - 1].strip().startswith("box_min:")


def test_station_pose_wrong_length(tmp_path):
    data = station_dict()
    data["frames"]["tool_in_opr"] = [0, 0, 0.07]
    problems, lines = _station_problems(tmp_path, data)
    assert "frames.tool_in_opr: list should have at least 6 items" in problems[0]
    assert lines[int(problems[0].split(":")[1]) - 1].strip().startswith("tool_in_opr")


def test_fake_station_is_valid(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump(station_dict()))
    assert load_station(path, check_geometry=False).name == "fake cell"


def test_committed_schemas_match_the_models():
    for name, schema in json_schemas().items():
        committed = json.loads((SCHEMA_DIR / f"{name}.json").read_text())
        assert committed == json.loads(json.dumps(schema)), \
            f"regenerate with python -m procedures.engine.write_schemas ({name})"
