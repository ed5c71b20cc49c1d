"""Building the twins' settings dataclasses from plain mappings (the cell YAML and test code).

The twins check their own configuration: a typo in a cell file must be reported as such (the
unknown key and the known ones) instead of as a ``TypeError`` from a constructor, or, worse, be
ignored. The drivers check the station file with their own models; nothing is shared, so the
twins stay independent of the drivers' code.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields, is_dataclass
from typing import Any


def checked_fields(cls: type, data: Mapping[str, Any] | None, what: str) -> dict[str, Any]:
    """``data`` as a new dict, after checking that every key names a field of dataclass ``cls``.

    Parameters
    ----------
    cls : type
        A dataclass.
    data : mapping or None
        The settings (None: no settings, all defaults).
    what : str
        How the error names the section (``"UR twin config"``).

    Returns
    -------
    dict
        A copy of ``data``.

    Raises
    ------
    ValueError
        Naming ``what``, the unknown keys and the known ones; also when ``data`` is not a mapping.
    """
    if not is_dataclass(cls):
        raise TypeError(f"checked_fields needs a dataclass, got {cls!r}")
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise ValueError(f"{what}: expected a mapping of settings, got {type(data).__name__}")
    result = dict(data)
    known = {f.name for f in fields(cls)}
    unknown = set(result) - known
    if unknown:
        raise ValueError(f"{what}: unknown field(s) {sorted(unknown)}; expected some of {sorted(known)}")
    return result
