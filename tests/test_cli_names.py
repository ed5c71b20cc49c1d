"""Names and values are checked before anything starts: a typo'd procedure or a bad ``--set`` is one line,
and no simulated cell is started for it (no ``<runs>/sim`` folder, no twin processes)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest


def _instrument(tmp_path: Path, *argv: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "INSTRUMENT_RUNS": str(tmp_path / "runs")}
    env.pop("INSTRUMENT_STORE", None)
    return subprocess.run([sys.executable, "-m", "procedures.cli", *argv], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize(("argv", "expected"), [
    (["iso9283_repeatibility"], "iso9283_repeatibility: no such procedure file (and no built-in procedure of "
                                "that name; did you mean iso9283_repeatability? built-ins: angle_calibration,"),
    (["iso9283_repeatability", "--set", "cyclez=3"], "--set cyclez=3"),
    (["iso9283_repeatability", "--set", "cycles=thirty"], "--set cycles=thirty: parameters.cycles"),
    (["iso9283_repeatability", "--set", "cycles=" + "9" * 5000],
     "--set cycles=99999999999999999999...: cannot read the value: a number of 5000 characters"),
])
def test_a_bad_name_or_value_starts_no_cell(tmp_path, argv, expected):
    result = _instrument(tmp_path, "run", *argv, "--station", "sim")
    assert result.returncode == 1
    assert result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(expected), result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "runs" / "sim").exists()  # no simulated cell was started


def test_validate_names_a_typo_too(tmp_path):
    result = _instrument(tmp_path, "validate", "iso9283_repeatability", "angle_calibraton")
    assert result.returncode == 1
    assert result.stdout.splitlines() == ["iso9283_repeatability: OK (iso9283_repeatability)"]
    assert result.stderr.splitlines() == [
        "angle_calibraton: no such procedure file (and no built-in procedure of that name; did you mean "
        "angle_calibration? built-ins: angle_calibration, displacement_calibration, iso9283_path, "
        "iso9283_repeatability, iso9283_stabilisation)"]
    result = _instrument(tmp_path, "validate", "nowhere/station.yaml")
    assert result.stderr.splitlines() == ["nowhere/station.yaml: cannot read YAML file: No such file or directory"]
