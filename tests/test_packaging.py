"""Packaging: the measurement core needs numpy, scipy and OpenCV only; everything else is an extra.

The import test runs in a fresh virtual environment that holds nothing but those three
distributions (linked from this one, so no download), and checks that every module of
``instrument`` imports there while pydantic, the client libraries and the servers cannot.
"""

from __future__ import annotations

import importlib.metadata
import subprocess
import sys
import sysconfig
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CORE_DISTRIBUTIONS = ("numpy", "scipy", "opencv-python-headless")
NOT_IN_THE_CORE = ("pydantic", "yaml", "rich", "rtde_control", "pypylon", "pymodbus", "can", "serial", "fastapi",
                   "asyncua", "weasyprint", "psycopg")


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def _name(requirement: str) -> str:
    for stop in "<>=![ ;":
        requirement = requirement.split(stop)[0]
    return requirement.strip().lower()


def test_the_core_depends_on_numpy_scipy_and_opencv_only_and_all_gives_every_extra():
    project = _pyproject()["project"]
    assert sorted(_name(r) for r in project["dependencies"]) == sorted(CORE_DISTRIBUTIONS)
    extras = project["optional-dependencies"]
    everything = extras["all"][0]
    named = set(everything[everything.index("[") + 1:everything.index("]")].split(","))
    # 'aravis' builds PyGObject against the OS's libraries: the Makefile installs it where it can.
    assert named == set(extras) - {"all", "test", "aravis"}, "'all' must name every other extra but test and aravis"


def _linked_core_venv(target: Path) -> Path:
    """A venv whose site-packages links only the core distributions' top-level files and folders."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(target)], check=True, timeout=120)
    python = target / "bin" / "python"
    site = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               check=True, capture_output=True, text=True, timeout=60).stdout.strip())
    here = Path(sysconfig.get_paths()["purelib"])
    for distribution in CORE_DISTRIBUTIONS:
        files = importlib.metadata.distribution(distribution).files or []
        for top in {Path(str(f)).parts[0] for f in files}:
            source = here / top
            if source.exists() and not (site / top).exists() and not top.endswith(".dist-info"):
                (site / top).symlink_to(source)
    (site / "project.pth").write_text(str(ROOT) + "\n", encoding="utf-8")
    return python


@pytest.mark.timeout(300)
def test_instrument_imports_without_any_extra(tmp_path):
    python = _linked_core_venv(tmp_path / "core")
    script = f"""
import importlib, importlib.util, pkgutil
import instrument
names = [m.name for m in pkgutil.walk_packages(instrument.__path__, "instrument.")]
for name in names:
    importlib.import_module(name)
present = [m for m in {NOT_IN_THE_CORE!r} if importlib.util.find_spec(m) is not None]
print(len(names), present)
"""
    done = subprocess.run([str(python), "-c", script], capture_output=True, text=True, timeout=240, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    count, present = done.stdout.split(" ", 1)
    assert int(count) > 30  # every module of the core imported
    assert present.strip() == "[]", f"the core venv must not see {present}"
