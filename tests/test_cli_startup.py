"""The command line starts at once: ``--version``, ``--help`` and the commands that only read the store
load neither the measurement core (numpy, scipy, OpenCV) nor the drivers, pydantic, the display or the
engine's stack. Each command runs in a fresh interpreter, which then lists the modules it loaded.
"""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(__file__).parent / "data"

# Run ``main`` as the ``instrument`` script does, then write the names of the loaded modules to a file.
PROBE = """
import json, sys
from procedures.cli import main
try:
    status = main(sys.argv[2:])
except SystemExit as exc:  # --version and --help end in argparse's exit
    status = exc.code
with open(sys.argv[1], "w") as out:
    json.dump({"status": status, "modules": sorted(sys.modules)}, out)
"""
HEAVY = ("numpy", "scipy", "cv2", "pydantic", "yaml", "rich", "drivers", "sim_devices", "asyncio",
         "procedures.engine", "procedures.report", "procedures.kinds", "procedures.serve",
         "procedures.cli._display", "instrument.pose", "instrument.vision", "instrument.iso9283")


def _loaded(tmp_path: Path, *argv: str) -> tuple[int, list[str]]:
    result_file = tmp_path / "modules.json"
    env = {**os.environ, "INSTRUMENT_RUNS": str(tmp_path / "runs")}
    env.pop("INSTRUMENT_STORE", None)
    subprocess.run([sys.executable, "-c", PROBE, str(result_file), *argv], cwd=tmp_path, env=env,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=120, check=False)
    data = json.loads(result_file.read_text())
    return data["status"], data["modules"]


def _heavy(modules: list[str]) -> list[str]:
    return [m for m in modules if any(m == h or m.startswith(h + ".") for h in HEAVY)]


def _stored_runs(tmp_path: Path) -> Path:
    runs = tmp_path / "runs"
    runs.mkdir()
    db = sqlite3.connect(runs / "runs.sqlite")
    db.executescript((DATA / "runs_stored_by_410f450.sql").read_text(encoding="utf-8"))
    db.close()
    return runs


@pytest.mark.parametrize("argv", [["--version"], ["--help"], ["run", "--help"], ["resume", "--help"],
                                  ["validate", "--help"], ["serve", "--help"], ["history", "--help"], []])
def test_version_and_help_load_nothing_heavy(tmp_path, argv):
    status, modules = _loaded(tmp_path, *argv)
    assert status in (0, 2)
    assert "procedures.cli" in modules
    assert _heavy(modules) == []


def test_reading_the_store_loads_nothing_heavy(tmp_path):
    runs = _stored_runs(tmp_path)
    status, modules = _loaded(tmp_path, "runs", "--runs-dir", str(runs))
    assert status == 0
    assert "procedures.store" in modules
    assert _heavy(modules) == []
    status, modules = _loaded(tmp_path, "runs", "--runs-dir", str(tmp_path / "nowhere"))
    assert status == 1 and _heavy(modules) == []


def test_run_help_lists_the_engines_built_in_procedures(capsys):
    """``run --help`` lists the built-in procedures without loading the engine: the same ones it resolves."""
    from procedures.cli import main
    from procedures.engine import PACKAGE_DIR

    with pytest.raises(SystemExit):
        main(["run", "--help"])
    names = sorted(path.stem for path in PACKAGE_DIR.glob("*.yaml"))
    assert len(names) >= 5
    assert f"a built-in name ({', '.join(names)})" in " ".join(capsys.readouterr().out.split())


def test_lazy_names_resolve():
    """Every public name of the packages that load their modules on first use is there (and is the same
    object as the private module's)."""
    import importlib

    for package in ("procedures.cli", "procedures.station"):
        module = importlib.import_module(package)
        for name in module.__all__:
            assert getattr(module, name) is not None, (package, name)
    with pytest.raises(AttributeError):
        importlib.import_module("procedures.station").no_such_name  # noqa: B018


def test_validating_files_loads_no_measurement_core(tmp_path):
    """``validate`` of procedure files needs the files' models (pydantic, the drivers' settings), not scipy,
    OpenCV, the science, the step context or the report."""
    status, modules = _loaded(tmp_path, "validate", "iso9283_repeatability", "angle_calibration", "iso9283_path")
    assert status == 0
    assert "procedures.kinds" in modules
    core = ("scipy", "cv2", "rich", "sim_devices", "asyncio", "procedures.report", "procedures.serve",
            "procedures.station._science", "procedures.engine._step_context", "procedures.engine._live_frames",
            "instrument.vision", "instrument.pose", "instrument.compensation")
    assert [m for m in modules if any(m == c or m.startswith(c + ".") for c in core)] == []
