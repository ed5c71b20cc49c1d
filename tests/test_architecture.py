"""The layout's import rules, checked on the source (an import anywhere, even inside a function)."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

FORBIDDEN = {
    "instrument": {"drivers", "sim_devices", "procedures"},  # the core is pure
    "drivers": {"sim_devices", "procedures"},
    "sim_devices": {"instrument", "procedures"},  # twins' physics written independently
}


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) in (
            "import_module",
            "__import__",
        ):
            if node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str):
                names.add(node.args[0].value.split(".")[0].split(":")[0])
    return names


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_package_respects_import_rules(package):
    offenders = []
    for path in sorted((ROOT / package).rglob("*.py")):
        bad = _imports(path) & FORBIDDEN[package]
        if bad:
            offenders.append(f"{path.relative_to(ROOT)} imports {sorted(bad)}")
    assert not offenders, "\n".join(offenders)


def test_instrument_does_no_io():
    """The measurement core opens no files and no sockets."""
    offenders = []
    for path in sorted((ROOT / "instrument").rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "open":
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno} calls open()")
        if _imports(path) & {"socket", "serial", "can", "pymodbus", "sqlite3", "subprocess", "pypylon"}:
            offenders.append(f"{path.relative_to(ROOT)} imports an I/O module")
    assert not offenders, "\n".join(offenders)
