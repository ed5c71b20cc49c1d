"""Device settings in a station file are checked by ``instrument validate`` before anything runs.

For every adapter: a typo in a setting, a wrong adapter name and a wrong type, each reported as
``station.yaml:LINE: devices.<role>.<setting>: ...`` with the allowed names, exit code 1 and no
traceback; through ``procedures.engine.load_station``, through ``procedures.cli.main`` and
once through the ``instrument`` command in its own process. Plus: the station the simulated
cell writes validates, and the published schema shows every adapter's fields.
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from drivers.camera import AravisSettings, PylonSettings
from drivers.interferometer import SlcanSettings, SocketcandSettings
from drivers.robot import ABBRwsSettings, URRtdeSettings
from drivers.rotary_table import GcsSerialSettings, GcsTcpSettings, ModbusRtuSettings, ModbusTcpSettings
from procedures.cli import main
from procedures.engine import SCHEMA_DIR, load_station
from procedures.station import ConfigError
from tests.fakes import station_dict


@dataclass(frozen=True)
class Adapter:
    """One adapter, where it sits in the station file, a valid entry and two bad values."""

    model: type
    path: tuple[str, ...]  # the device entry's keys under ``devices``
    entry: dict
    typo: tuple[str, object]  # a misspelt setting and its value
    wrong_type: tuple[str, object]  # a real setting with a value of the wrong type
    expected_type: str  # the start of pydantic's words for the wrong type
    wrong_adapter: str
    all_adapters: str  # the adapters of this device kind, as the message lists them

    @property
    def name(self) -> str:
        return self.entry["adapter"]


ADAPTERS = [
    Adapter(URRtdeSettings, ("robot",), {"adapter": "ur_rtde", "host": "127.0.0.2"}, ("hots", "127.0.0.3"),
            ("frequency", "fast"), "input should be a valid number", "ur_rtd", "ur_rtde, abb_rws"),
    Adapter(ABBRwsSettings, ("robot",), {"adapter": "abb_rws", "base_url": "http://127.0.0.3:80"},
            ("base_ulr", "http://127.0.0.3"), ("egm_port", "six"), "input should be a valid integer", "abb_rsw",
            "ur_rtde, abb_rws"),
    Adapter(PylonSettings, ("cameras", "y"), {"adapter": "pylon", "serial": "0815-0001"}, ("exposure", 0.002),
            ("exposure_s", "long"), "input should be a valid number", "pylonn", "pylon, aravis"),
    Adapter(AravisSettings, ("cameras", "z"), {"adapter": "aravis", "address": "127.0.0.5"}, ("adress", "127.0.0.6"),
            ("buffers", "many"), "input should be a valid integer", "arvis", "pylon, aravis"),
    Adapter(ModbusTcpSettings, ("rotary_table",), {"adapter": "modbus_tcp", "host": "127.0.0.1", "port": 502},
            ("prot", 502), ("port", "five-o-two"), "input should be a valid integer", "modbus_tpc",
            "modbus_tcp, modbus_rtu, gcs_serial, gcs_tcp"),
    Adapter(ModbusRtuSettings, ("rotary_table",), {"adapter": "modbus_rtu", "port": "/dev/ttyUSB0"},
            ("baud", 115200), ("unit", [1]), "input should be a valid integer", "modbus_rut",
            "modbus_tcp, modbus_rtu, gcs_serial, gcs_tcp"),
    Adapter(GcsSerialSettings, ("rotary_table",), {"adapter": "gcs_serial", "port": "/dev/ttyUSB1", "axis": "1"},
            ("axes", "1"), ("baudrate", "fast"), "input should be a valid integer", "gcs",
            "modbus_tcp, modbus_rtu, gcs_serial, gcs_tcp"),
    Adapter(GcsTcpSettings, ("rotary_table",), {"adapter": "gcs_tcp", "host": "127.0.0.1", "port": 50000},
            ("hostname", "127.0.0.2"), ("reference_on_open", "sometimes"), "input should be a valid boolean",
            "gcs_tpc", "modbus_tcp, modbus_rtu, gcs_serial, gcs_tcp"),
    Adapter(SocketcandSettings, ("interferometer",),
            {"adapter": "socketcand", "host": "127.0.0.1", "port": 29536, "channel": "can0"},
            ("chanel", "can1"), ("open_attempts", "many"), "input should be a valid integer", "socketcan",
            "socketcand, slcan"),
    Adapter(SlcanSettings, ("interferometer",), {"adapter": "slcan", "port": "/dev/ttyACM0"},
            ("bitrat", 500000), ("sync_before_average", "sometimes"), "input should be a valid boolean", "slcn",
            "socketcand, slcan"),
]
CASES = ["typo", "wrong_adapter", "wrong_type"]


def _station(adapter: Adapter, case: str) -> dict:
    entry = dict(adapter.entry)
    if case == "typo":
        entry[adapter.typo[0]] = adapter.typo[1]
    elif case == "wrong_adapter":
        entry["adapter"] = adapter.wrong_adapter
    else:
        entry[adapter.wrong_type[0]] = adapter.wrong_type[1]
    data = station_dict()
    holder = data["devices"]
    for key in adapter.path[:-1]:
        holder = holder[key]
    holder[adapter.path[-1]] = entry
    return data


def _line_of(text: str, keys: tuple[str, ...]) -> int:
    """The 1-based line of the key path ``keys`` in block YAML, found by indentation alone."""
    lines = text.splitlines()
    start, indent = 0, -1
    for key in keys:
        for number in range(start, len(lines)):
            line = lines[number]
            depth = len(line) - len(line.lstrip())
            if depth > indent and line.strip().startswith(f"{key}:"):
                start, indent = number + 1, depth
                break
        else:
            raise AssertionError(f"{'.'.join(keys)} not found")
    return start


def _expected(adapter: Adapter, case: str, path: Path) -> tuple[int, str]:
    """The line and the message ``instrument validate`` must print for this bad file."""
    text = path.read_text()
    where = ("devices", *adapter.path)
    field = ".".join(where)
    if case == "typo":
        allowed = ", ".join(name for name in adapter.model.model_fields if name != "adapter")
        key = adapter.typo[0]
        message = f"{field}.{key}: unknown field; expected one of {allowed}"
    elif case == "wrong_adapter":
        key = "adapter"
        message = f"{field}.adapter: expected one of {adapter.all_adapters} (got {adapter.wrong_adapter!r})"
    else:
        key = adapter.wrong_type[0]
        message = f"{field}.{key}: {adapter.expected_type}"
    return _line_of(text, (*where, key)), message


@pytest.fixture(params=[(a, c) for a in ADAPTERS for c in CASES], ids=lambda p: f"{p[0].name}-{p[1]}")
def bad_station(request, tmp_path):
    adapter, case = request.param
    path = tmp_path / "station.yaml"
    path.write_text(yaml.safe_dump(_station(adapter, case), sort_keys=False))
    line, message = _expected(adapter, case, path)
    return path, f"{path}:{line}: {message}"


def test_load_station_names_file_line_field_and_the_allowed_names(bad_station):
    path, expected = bad_station
    with pytest.raises(ConfigError) as caught:
        load_station(path, check_geometry=False)
    assert len(caught.value.problems) == 1, caught.value.problems
    assert caught.value.problems[0].startswith(expected), (caught.value.problems[0], expected)


def test_validate_command_reports_it_and_fails(bad_station, capsys):
    path, expected = bad_station
    assert main(["validate", str(path)]) == 1
    out, err = capsys.readouterr()
    assert err.startswith(expected) and len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in out + err and "OK" not in out


def test_the_good_entries_validate(tmp_path):
    """The base entries of the cases above are valid: each bad file differs by its one bad value."""
    for adapter in ADAPTERS:
        data = station_dict()
        holder = data["devices"]
        for key in adapter.path[:-1]:
            holder = holder[key]
        holder[adapter.path[-1]] = adapter.entry
        path = tmp_path / f"{adapter.name}.yaml"
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        station = load_station(path, check_geometry=False)
        device = station.devices
        for key in adapter.path:
            device = getattr(device, key)
        assert isinstance(device, adapter.model) and device.adapter == adapter.name


def test_numbers_for_text_settings_are_read_as_text(tmp_path):
    """YAML reads a numeric camera serial or GCS axis as an int; the station still loads."""
    path = tmp_path / "station.yaml"
    text = yaml.safe_dump(station_dict(), sort_keys=False).replace("serial: fake-x", "serial: 21234567")
    path.write_text(text)
    assert load_station(path, check_geometry=False).devices.cameras.x.serial == "21234567"


def test_instrument_validate_in_its_own_process(tmp_path):
    """The installed command, one process, every bad file: one line each, exit 1, no traceback."""
    expected = []
    for adapter in ADAPTERS:
        for case in CASES:
            path = tmp_path / f"{adapter.name}-{case}.yaml"
            path.write_text(yaml.safe_dump(_station(adapter, case), sort_keys=False))
            line, message = _expected(adapter, case, path)
            expected.append(f"{path}:{line}: {message}")
    files = sorted(tmp_path.glob("*.yaml"))
    result = subprocess.run([sys.executable, "-m", "procedures.cli", "validate", *map(str, files)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 1
    assert "Traceback" not in result.stdout + result.stderr
    problems = result.stderr.strip().splitlines()
    assert len(problems) == len(expected)
    for line in expected:
        assert any(problem.startswith(line) for problem in problems), line


def test_the_station_the_simulated_cell_writes_validates(tmp_path):
    from sim_devices.cell import SimCell

    with SimCell(seed=3, directory=tmp_path / "cell") as cell:
        station = load_station(cell.station_path)  # geometry checked too
        assert main(["validate", str(cell.station_path)]) == 0
    assert isinstance(station.devices.robot, URRtdeSettings)
    assert all(isinstance(getattr(station.devices.cameras, s), PylonSettings) for s in "xyz")
    assert isinstance(station.devices.rotary_table, ModbusTcpSettings)
    assert isinstance(station.devices.interferometer, SocketcandSettings)


def test_the_published_schema_shows_every_adapters_fields():
    schema = json.loads((SCHEMA_DIR / "station.json").read_text())
    definitions = schema["$defs"]
    for adapter in ADAPTERS:
        published = definitions[adapter.model.__name__]
        assert set(published["properties"]) == set(adapter.model.model_fields), adapter.name
        assert published["additionalProperties"] is False and "adapter" in published["required"]
        assert all(p.get("description") for p in published["properties"].values()), adapter.name
    devices = definitions["DevicesConfig"]["properties"]
    cameras = definitions["CamerasConfig"]["properties"]

    def tags(entry: dict) -> set[str]:
        union = next((e for e in entry.get("anyOf", [entry]) if "discriminator" in e), entry)
        assert union["discriminator"]["propertyName"] == "adapter"
        return set(union["discriminator"]["mapping"])

    assert tags(devices["robot"]) == {"ur_rtde", "abb_rws"}
    assert all(tags(cameras[s]) == {"pylon", "aravis"} for s in "xyz")
    assert tags(devices["rotary_table"]) == {"modbus_tcp", "modbus_rtu", "gcs_serial", "gcs_tcp"}
    assert tags(devices["interferometer"]) == {"socketcand", "slcan"}
    # The data formats a station may carry are in it too, field by field.
    assert {"word_order", "counts_per_rev", "status_bits"} <= set(definitions["RegisterMap"]["properties"])
    assert {"displacement_id", "resolution", "sample_rate"} <= set(definitions["FrameLayout"]["properties"])
