"""Building configuration dataclasses from plain mappings (station and cell YAML)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields
from typing import Any


def checked_fields(cls: type, data: Mapping[str, Any] | None, what: str) -> dict[str, Any]:
    """``data`` as a new dict, after checking that every key names a field of dataclass ``cls``.

    Raises
    ------
    ValueError
        Naming ``what``, the unknown keys and the known ones, so a typo in a YAML file is reported
        as such instead of as a ``TypeError`` from the constructor.
    """
    data = dict(data or {})
    known = {f.name for f in fields(cls)}
    unknown = set(data) - known
    if unknown:
        raise ValueError(f"{what}: unknown field(s) {sorted(unknown)}; expected some of {sorted(known)}")
    return data
