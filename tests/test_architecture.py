"""The layout's import contract, checked on the source (an import anywhere, even inside a function).

The rules, each failure naming the file, the line and the import (or the literal):

1. Layers: the measurement core imports none of the other packages; drivers never import the
   twins or the procedures; the twins never import the core or the procedures.
2. Public seams: a package uses another package only through its public names. Importing a
   ``_private`` module (or a ``_private`` name) of another package is a violation, wherever the
   underscore sits in the dotted path.
3. Twins independent of the drivers' protocol code: from ``drivers`` the twins may use only the
   shared errors and the camera interface (the in-process ``SimCamera`` implements it); never a
   driver's register map, frame layout or client code, so that a convention error on either side
   fails a test instead of cancelling out.
4. Layers inside ``procedures`` (``PROCEDURES_LAYERS``): each subpackage imports only the subpackages
   below it — cli → serve, engine, report, store (and below); serve → engine, report, store; engine →
   kinds, store; report → kinds, store; kinds → store; store → station; station → nothing of procedures.
   So the kinds never import the report, the engine or the faces.
5. Private modules are private to their package, inside ``procedures`` too: ``procedures.a.b._c`` may be
   imported only by modules of ``procedures.a.b`` (a family of kinds may use ``procedures.kinds._protocol``,
   the report may not; ``kinds/iso`` may not reach into ``kinds/calibration``). The tests and the
   benchmarks import ``procedures`` through public names only (``TESTS_MAY_REACH_IN`` lists the exception).
6. No module outside ``procedures/kinds/`` names a kind in code: no string literal that *is* a kind's name
   (``"iso9283_repeatability"``), wherever it stands (a comparison, a dict key, a constant, a part of an
   f-string). Docstrings are not code, and prose that mentions a kind inside a longer text (a help text,
   an example command in a message) is not a literal *equal* to the name, so both may. The demo, which
   runs named procedures, is the one module allowed (``MAY_NAME_KINDS``).
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


# Inside procedures: subpackage → the subpackages it may import (it may always import itself).
PROCEDURES_LAYERS = {
    "cli": {"serve", "engine", "report", "kinds", "store", "station"},
    "serve": {"engine", "report", "kinds", "store", "station"},
    "engine": {"kinds", "store", "station"},
    "report": {"kinds", "store", "station"},
    "kinds": {"store", "station"},
    "store": {"station"},
    "station": set(),
}
# Modules at procedures' top: the demo runs the whole stack; ``python -m procedures`` is the command line.
PROCEDURES_TOP = {"demo": set(PROCEDURES_LAYERS), "__main__": {"cli"}, "__init__": set()}
TESTS_MAY_REACH_IN = {
    "tests/data/make_runs_stored_by_410f450.py": "runs against commit 410f450, whose procedures had no public names",
}
MAY_NAME_KINDS = {"procedures/demo.py": "runs the calibrations and the ISO cycle by their names"}


def _module_of(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _private_owner(module: str) -> str | None:
    """The package a ``_private`` module belongs to (``procedures.kinds.iso._budget`` → ``procedures.kinds.iso``),
    or None for a public dotted path."""
    parts = module.split(".")
    for i, part in enumerate(parts):
        if _is_private(part):
            return ".".join(parts[:i])
    return None


def _layer_offences(path: Path, imp: Import) -> list[str]:
    """What is wrong with one import of ``procedures`` by a module of ``procedures`` (rules 4 and 5)."""
    parts = imp.module.split(".")
    if parts[0] != "procedures" or len(parts) < 2:
        return []
    here = path.relative_to(ROOT / "procedures").with_suffix("").parts
    mine, target = here[0], parts[1]
    allowed = PROCEDURES_LAYERS.get(mine, PROCEDURES_TOP.get(mine, set()))
    offences = []
    if target in PROCEDURES_LAYERS and target != mine and target not in allowed:
        offences.append(f"{imp} (layer: procedures.{mine} must not import procedures.{target})")
    owner = _private_owner(imp.module)
    module = _module_of(path)
    if owner is not None and not (module == owner or module.startswith(owner + ".")):
        offences.append(f"{imp} (private to {owner})")
    private_names = [n for n in imp.names if _is_private(n)]
    if private_names and not (module == imp.module or module.startswith(imp.module + ".")):
        offences.append(f"{imp} (private names of {imp.module}: {', '.join(private_names)})")
    return offences


def _procedures_offences(files: list[Path]) -> list[str]:
    return [offence for path in files for imp in _imports(path) for offence in _layer_offences(path, imp)]


def _is_private(part: str) -> bool:
    return part.startswith("_") and not (part.startswith("__") and part.endswith("__"))


def test_contract_checker_catches_violations(tmp_path):
    """The checker itself: a private reach-in and a forbidden layer are both reported with the line."""
    module = tmp_path / "probe.py"
    module.write_text("import os\nfrom drivers.robot._ur import URRobot\n\ndef f():\n    import procedures\n")
    imports = _imports(module)
    assert [(i.line, i.module) for i in imports] == [(1, "os"), (2, "drivers.robot._ur"), (5, "procedures")]
    assert any(_is_private(part) for part in imports[1].module.split("."))


def test_procedures_checker_catches_violations():
    """Rules 4–6 on probes placed as if they were modules of procedures (never written to the tree)."""
    kinds_module = ROOT / "procedures" / "kinds" / "iso" / "_probe.py"
    report_module = ROOT / "procedures" / "report" / "_probe.py"

    def offences(path: Path, source: str) -> list[str]:
        tree = ast.parse(source)
        found = []
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module:
                imp = Import(path, node.lineno, node.module, tuple(a.name for a in node.names))
                found += _layer_offences(path, imp)
        return found

    assert offences(kinds_module, "from procedures.kinds._protocol import Step\n") == []  # its own package
    assert offences(kinds_module, "def f():\n    from procedures.report import render_report\n") == [
        "procedures/kinds/iso/_probe.py:2: from procedures.report import render_report "
        "(layer: procedures.kinds must not import procedures.report)"]
    assert offences(kinds_module, "from procedures.kinds.calibration._common import line_points\n") == [
        "procedures/kinds/iso/_probe.py:1: from procedures.kinds.calibration._common import line_points "
        "(private to procedures.kinds.calibration)"]
    assert offences(report_module, "from procedures.kinds._protocol import Step\n") == [
        "procedures/report/_probe.py:1: from procedures.kinds._protocol import Step (private to procedures.kinds)"]
    assert offences(report_module, "from procedures.kinds import _KINDS\n") == [
        "procedures/report/_probe.py:1: from procedures.kinds import _KINDS (private names of procedures.kinds: "
        "_KINDS)"]
    names = {"iso9283_repeatability"}
    assert _kind_literals(kinds_module, 'X = "iso9283_repeatability"\n', names) == [
        "procedures/kinds/iso/_probe.py:1: 'iso9283_repeatability'"]
    assert _kind_literals(report_module, '"""Docstring: iso9283_repeatability."""\nHELP = "e.g. '
                                         'iso9283_repeatability"\n', names) == []


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


def test_procedures_layers_and_private_modules():
    """Rules 4 and 5 over every module of procedures."""
    offenders = _procedures_offences(_package_files("procedures"))
    assert not offenders, "\n".join(offenders)


def test_tests_and_benchmarks_use_public_names_of_procedures():
    offenders = []
    for path in sorted((ROOT / "tests").rglob("*.py")) + sorted((ROOT / "benchmarks").rglob("*.py")):
        if str(path.relative_to(ROOT)) in TESTS_MAY_REACH_IN:
            continue
        for imp in _imports(path):
            if imp.module.split(".")[0] != "procedures":
                continue
            private = [p for p in imp.module.split(".") if _is_private(p)] + [n for n in imp.names if _is_private(n)]
            if private:
                offenders.append(f"{imp} (private to procedures: {', '.join(private)})")
    assert not offenders, "\n".join(offenders)


def _docstrings(tree: ast.AST) -> set[int]:
    """The ids of the string constants that are docstrings (of the module, a class or a function)."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(
                    first.value.value, str):
                found.add(id(first.value))
    return found


def _kind_literals(path: Path, source: str, names: set[str]) -> list[str]:
    """Rule 6: every string literal of ``source`` (not a docstring) that is a kind's name, as ``file:line: 'name'``."""
    tree = ast.parse(source)
    docstrings = _docstrings(tree)
    return [f"{path.relative_to(ROOT)}:{node.lineno}: {node.value!r}" for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in names
            and id(node) not in docstrings]


def test_no_module_outside_the_kinds_names_a_kind():
    from procedures.kinds import KINDS

    names = set(KINDS)
    offenders = []
    for path in _package_files("procedures"):
        relative = str(path.relative_to(ROOT))
        if relative.startswith("procedures/kinds/") or relative in MAY_NAME_KINDS:
            continue
        offenders += _kind_literals(path, path.read_text(encoding="utf-8"), names)
    assert not offenders, "a kind named outside procedures/kinds/ (declare it on the kind instead):\n" + "\n".join(
        offenders)
