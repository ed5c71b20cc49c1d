"""RAPID data values as RWS carries them: aggregate literals such as
``[TRUE,[[0,0,0.08],[1,0,0,0]],[2.5,[0,0,50],[1,0,0,0],0,0,0]]`` (a ``tooldata``).

``parse_value`` turns a literal into nested Python lists of floats, bools and strings;
``format_value`` writes them back the way the controller shows them (numbers with up to nine
significant digits, ``TRUE``/``FALSE``, strings in double quotes).
"""

from __future__ import annotations

import re
from typing import Any

_TOKEN = re.compile(r'\s*(?:(\[)|(\])|(,)|("(?:[^"]|"")*")|(TRUE|FALSE)|([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?))',
                    re.IGNORECASE)


class RapidValueError(ValueError):
    """A text that is not a RAPID value literal."""


def parse_value(text: str) -> Any:
    """The value of a RAPID literal (see the module docstring)."""
    tokens: list[tuple[str, str]] = []
    position = 0
    text = text.strip()
    while position < len(text):
        match = _TOKEN.match(text, position)
        if match is None or match.end() == position:
            raise RapidValueError(f"not a RAPID value: {text!r} (at character {position})")
        kind = ("open", "close", "comma", "string", "bool", "num")[match.lastindex - 1]  # type: ignore[operator]
        tokens.append((kind, match.group(match.lastindex or 0)))
        position = match.end()
    value, used = _parse(tokens, 0, text)
    if used != len(tokens):
        raise RapidValueError(f"not a RAPID value: {text!r} (trailing text)")
    return value


def _parse(tokens: list[tuple[str, str]], i: int, text: str) -> tuple[Any, int]:
    if i >= len(tokens):
        raise RapidValueError(f"not a RAPID value: {text!r} (ends early)")
    kind, raw = tokens[i]
    if kind == "num":
        return float(raw), i + 1
    if kind == "bool":
        return raw.upper() == "TRUE", i + 1
    if kind == "string":
        return raw[1:-1].replace('""', '"'), i + 1
    if kind != "open":
        raise RapidValueError(f"not a RAPID value: {text!r} (unexpected {raw!r})")
    items: list[Any] = []
    i += 1
    if i < len(tokens) and tokens[i][0] == "close":
        return items, i + 1
    while True:
        item, i = _parse(tokens, i, text)
        items.append(item)
        if i >= len(tokens):
            raise RapidValueError(f"not a RAPID value: {text!r} (unclosed bracket)")
        if tokens[i][0] == "close":
            return items, i + 1
        if tokens[i][0] != "comma":
            raise RapidValueError(f"not a RAPID value: {text!r} (expected a comma)")
        i += 1


def format_value(value: Any) -> str:
    """The RAPID literal of ``value`` (nested lists, floats, bools, strings)."""
    if isinstance(value, bool):
        return "TRUE" if value else "FALSE"
    if isinstance(value, (int, float)):
        number = float(value)
        return "0" if number == 0 else format(number, ".9g")
    if isinstance(value, str):
        return '"' + value.replace('"', '""') + '"'
    return "[" + ",".join(format_value(item) for item in value) + "]"


def tooldata_value(robhold: bool, trans_mm, quaternion, mass: float, cog_mm, aom=(1.0, 0.0, 0.0, 0.0),
                   inertia=(0.0, 0.0, 0.0)) -> list[Any]:
    """A ``tooldata`` value as nested lists."""
    return [bool(robhold), [list(map(float, trans_mm)), list(map(float, quaternion))],
            [float(mass), list(map(float, cog_mm)), list(map(float, aom)), *map(float, inertia)]]
