"""``--set key=value``: a procedure's parameters changed for one run, validated like the file.

The run stores the procedure text it really ran: the file's content with the overrides written into
its ``parameters`` and a first comment line naming them, so ``instrument show``, the report and a
resume all see the changed values. A value is read as a YAML scalar or list, as in the file
(``cycles=5``, ``save_frames=never``, ``cube_center_m=[0.03, 0.03, 0.03]``). A problem is one line
naming the override: ``--set cycles=thirty: parameters.cycles: input should be a valid integer``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from procedures.engine._loading import load_procedure
from procedures.kinds import ProcedureBase
from procedures.station import ConfigError, load_marked

MAX_OVERRIDE_CHARS = 10_000
_KEY = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_PROBLEM = re.compile(r"^.*?:\d+: parameters\.([A-Za-z0-9_]+)(.*)$")


def parse_set(items: list[str]) -> dict[str, tuple[str, Any]]:
    """``["cycles=5"]`` → ``{"cycles": ("cycles=5", 5)}``; raises ``ConfigError`` (one line each)."""
    parsed: dict[str, tuple[str, Any]] = {}
    problems = []
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if len(item) > MAX_OVERRIDE_CHARS:
            problems.append(f"--set {item[:40]}...: longer than {MAX_OVERRIDE_CHARS} characters")
        elif not sep or not _KEY.match(key):
            problems.append(f"--set {item}: expected PARAMETER=VALUE (a name from the procedure's parameters)")
        else:
            try:
                value = yaml.safe_load(text) if text.strip() else None
            except yaml.YAMLError as exc:
                problems.append(f"--set {item}: cannot read the value: {(str(exc).splitlines() or [''])[0]}")
                continue
            except ValueError:  # Python refuses to read an integer of more than 4300 digits
                problems.append(f"--set {key}={text[:20]}...: cannot read the value: a number of {len(text)} "
                                "characters")
                continue
            if isinstance(value, dict):
                problems.append(f"--set {item}: expected a number, a word, true/false or a [list]")
                continue
            parsed[key] = (item, value)
    if problems:
        raise ConfigError(problems)
    return parsed


def apply_overrides(path: Path, text: str, items: list[str]) -> tuple[str, ProcedureBase]:
    """The procedure text with ``items`` (``key=value``) in its parameters, and its validated model.

    Raises
    ------
    ConfigError
        An override is malformed, names no parameter, or gives a value the parameter refuses
        (one line per problem, naming the ``--set``); or the file itself is invalid.
    """
    overrides = parse_set(items)
    load_procedure(path, text)  # the file alone first: its own problems keep their file:line
    data = load_marked(path, text).data
    parameters = dict(data.get("parameters") or {})
    parameters.update({key: value for key, (_, value) in overrides.items()})
    data = {**data, "parameters": parameters}
    changed = " ".join(f"--set {item}" for item, _ in overrides.values())
    new_text = f"# {path.name} run with {changed}\n" + yaml.safe_dump(data, sort_keys=False, allow_unicode=True)
    try:
        return new_text, load_procedure(path, new_text)
    except ConfigError as exc:
        raise ConfigError([_named(problem, overrides) for problem in exc.problems]) from None


def _named(problem: str, overrides: dict[str, tuple[str, Any]]) -> str:
    match = _PROBLEM.match(problem)
    if match and match.group(1) in overrides:
        return f"--set {overrides[match.group(1)][0]}: parameters.{match.group(1)}{match.group(2)}"
    return problem
