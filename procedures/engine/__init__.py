"""The run engine: it drives any procedure kind through a run, one committed sample at a time.

What it offers:

- ``open_engine`` (a new run from a procedure and a station, or a stored one by id, with its lease and
  devices handled) and ``RunEngine`` itself, with ``create_run``, ``PauseDecision`` and the records in
  force (``record_paths``, ``compensators_in_force``);
- loading and validating procedure and station files with ``file:line`` messages (``load_procedure``,
  ``load_station``, ``resolve_procedure_path``, ``detect_kind``, ``json_schemas``, ``SCHEMA_DIR``,
  ``PACKAGE_DIR``) and ``--set`` overrides (``apply_overrides``);
- the dry run's checks (``offline_problems``, ``record_problems``, ``collapse``);
- the hooks (``HookRunner``, ``MAX_RESPONSE_BYTES``);
- the live frames the web view shows (``write_live_frames``, ``png_of``, ``LIVE_DIR``, ``LIVE_INDEX``,
  ``DEFAULT_SCALE``).

It knows no kind by name: it stands on ``procedures.kinds`` (the Protocol and the registry),
``procedures.store`` and ``procedures.station``. ``python -m procedures.engine.write_schemas`` writes the JSON
Schemas of the procedure and station files.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from procedures.engine._dry_run import collapse, offline_problems, record_problems
    from procedures.engine._engine import PauseDecision, RunEngine, compensators_in_force, create_run, record_paths
    from procedures.engine._hooks import MAX_RESPONSE_BYTES, HookRunner
    from procedures.engine._live_frames import DEFAULT_SCALE, LIVE_DIR, LIVE_INDEX, png_of, write_live_frames
    from procedures.engine._loading import (
        PACKAGE_DIR,
        SCHEMA_DIR,
        detect_kind,
        json_schemas,
        load_procedure,
        load_station,
        resolve_procedure_path,
    )
    from procedures.engine._open import open_engine
    from procedures.engine._overrides import apply_overrides

# Each module loads on first use of one of its names: loading a procedure file (``instrument validate``)
# needs neither the step context's measuring nor the live frames' OpenCV.
_LAZY = {
    **dict.fromkeys(("collapse", "offline_problems", "record_problems"), "_dry_run"),
    **dict.fromkeys(("PauseDecision", "RunEngine", "compensators_in_force", "create_run", "record_paths"), "_engine"),
    **dict.fromkeys(("MAX_RESPONSE_BYTES", "HookRunner"), "_hooks"),
    **dict.fromkeys(("DEFAULT_SCALE", "LIVE_DIR", "LIVE_INDEX", "png_of", "write_live_frames"), "_live_frames"),
    **dict.fromkeys(("PACKAGE_DIR", "SCHEMA_DIR", "detect_kind", "json_schemas", "load_procedure", "load_station",
                     "resolve_procedure_path"), "_loading"),
    "open_engine": "_open",
    "apply_overrides": "_overrides",
}


def __getattr__(name: str) -> Any:
    """A public name of a module not loaded yet: load it (once) and keep the name here."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


__all__ = [
    "DEFAULT_SCALE", "LIVE_DIR", "LIVE_INDEX", "MAX_RESPONSE_BYTES", "PACKAGE_DIR", "SCHEMA_DIR",
    "HookRunner", "PauseDecision", "RunEngine", "apply_overrides", "collapse", "compensators_in_force",
    "create_run", "detect_kind", "json_schemas", "load_procedure", "load_station", "offline_problems", "open_engine",
    "png_of", "record_paths", "record_problems", "resolve_procedure_path", "write_live_frames",
]
