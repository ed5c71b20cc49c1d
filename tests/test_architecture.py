"""The layout's import contract, checked on the source (an import anywhere, even inside a function).

Three rules, each failure naming the file, the line and the import:

1. Layers: the measurement core imports none of the other packages; drivers never import the
   twins or the procedures; the twins never import the core or the procedures.
2. Public seams: a package uses another package only through its public names. Importing a
   ``_private`` module (or a ``_private`` name) of another package is a violation, wherever the
   underscore sits in the dotted path.
3. Twins independent of the drivers' protocol code: from ``drivers`` the twins may use only the
   shared errors and the camera interface (the in-process ``SimCamera`` implements it); never a
   driver's register map, frame layout or client code, so that a convention error on either side
   fails a test instead of cancelling out.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("instrument", "drivers", "sim_devices", "procedures")

FORBIDDEN = {
    "instrument": {"drivers", "sim_devices", "procedures"},  # the core is pure
    "drivers": {"sim_devices", "procedures", "instrument"},
    "sim_devices": {"instrument", "procedures"},  # twins' physics written independently
}
# Modules of another package a package may import at all (when it may import that package).
ALLOWED_MODULES = {("sim_devices", "drivers"): {"drivers", "drivers.camera"}}


@dataclass(frozen=True)
class Import:
    path: Path
    line: int
    module: str  # the dotted module imported from (absolute)
    names: tuple[str, ...] = ()  # for ``from module import a, b``

    def __str__(self) -> str:
        what = f"from {self.module} import {', '.join(self.names)}" if self.names else f"import {self.module}"
        return f"{self.path.relative_to(ROOT)}:{self.line}: {what}"


def _imports(path: Path) -> list[Import]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found: list[Import] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [Import(path, node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append(Import(path, node.lineno, node.module, tuple(alias.name for alias in node.names)))
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) in (
            "import_module",
            "__import__",
        ):
            if node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str):
                found.append(Import(path, node.lineno, node.args[0].value.split(":")[0]))
    return found


def _package_files(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


def _is_private(part: str) -> bool:
    return part.startswith("_") and not (part.startswith("__") and part.endswith("__"))


def test_contract_checker_catches_violations(tmp_path):
    """The checker itself: a private reach-in and a forbidden layer are both reported with the line."""
    module = tmp_path / "probe.py"
    module.write_text("import os\nfrom drivers.robot._ur import URRobot\n\ndef f():\n    import procedures\n")
    imports = _imports(module)
    assert [(i.line, i.module) for i in imports] == [(1, "os"), (2, "drivers.robot._ur"), (5, "procedures")]
    assert any(_is_private(part) for part in imports[1].module.split("."))


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_layers(package):
    offenders = []
    for path in _package_files(package):
        for imp in _imports(path):
            top = imp.module.split(".")[0]
            if top in FORBIDDEN[package]:
                offenders.append(f"{imp} (layer: {package} must not import {top})")
            allowed = ALLOWED_MODULES.get((package, top))
            if allowed is not None and imp.module not in allowed:
                offenders.append(f"{imp} ({package} may import only {sorted(allowed)} of {top})")
    assert not offenders, "\n".join(offenders)


@pytest.mark.parametrize("package", PACKAGES)
def test_no_private_reach_ins(package):
    offenders = []
    for path in _package_files(package):
        for imp in _imports(path):
            parts = imp.module.split(".")
            if parts[0] not in PACKAGES or parts[0] == package:
                continue
            private = [p for p in parts[1:] if _is_private(p)] + [n for n in imp.names if _is_private(n)]
            if private:
                offenders.append(f"{imp} (private to {parts[0]}: {', '.join(private)})")
    assert not offenders, "\n".join(offenders)


def test_instrument_does_no_io():
    """The measurement core opens no files and no sockets."""
    offenders = []
    for path in _package_files("instrument"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "open":
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno} calls open()")
        io_modules = {"socket", "serial", "can", "pymodbus", "sqlite3", "subprocess", "pypylon"}
        for imp in _imports(path):
            if imp.module.split(".")[0] in io_modules:
                offenders.append(f"{imp} (an I/O module)")
    assert not offenders, "\n".join(offenders)
