"""The station and what everything above it shares: the bottom layer of ``procedures``.

What it offers:

- the station file's model (``StationFile``, ``HookSpec``, ``Event``, ``Vec3``) and its YAML with line
  marks (``load_marked``, ``MarkedYaml``), read with a size bound (``read_text_file``, ``InputRefused``);
- the devices of a station, opened on first use, and who mounts and aligns things (``StationRuntime``,
  ``Operator``);
- the measurement core bound to a station (``Science``, ``InstrumentScience``, ``Compensator``,
  ``PoseMeasurement``, ``MeasurementFailed``, ``CalibrationResult``) and which pose component each axis'
  rotation is (``ANGLE_COMPONENT``);
- the simulated cell's truth log (``TruthLog``);
- the geometry of UR and Euler poses (``ur_to_matrix``, ``tcp_in_m``, ``translated_in_frame`` ...);
- the errors of the procedure layer (``ConfigError``, ``RunError`` and its kinds).

It imports nothing of ``procedures`` above it (the kinds, the store, the engine, the report and the
faces all stand on it).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# The errors and the bounded file reading load with the package (every command may need them); the rest
# on first use (``__getattr__`` below), so that a command which only reads the store never loads the
# measurement core, pydantic or the drivers.
from procedures.station._errors import (
    ConfigError,
    DryRunFailed,
    ResumeRefused,
    RunAborted,
    RunError,
    RunLocked,
    StateConflict,
)
from procedures.station._files import InputRefused, read_text_file

if TYPE_CHECKING:
    from procedures.station._geometry import (
        ANGLE_COMPONENT,
        euler_to_matrix,
        matrix_to_euler,
        matrix_to_ur,
        tcp_in_m,
        translated_in_frame,
        ur_to_matrix,
    )
    from procedures.station._models import Event, HookSpec, StationFile, Vec3
    from procedures.station._runtime import Operator, StationRuntime
    from procedures.station._science import (
        CalibrationResult,
        Compensator,
        InstrumentScience,
        MeasurementFailed,
        PoseMeasurement,
        Science,
    )
    from procedures.station._truth import TruthLog
    from procedures.station._yamlmarks import MarkedYaml, load_marked

_LAZY = {
    **dict.fromkeys(("ANGLE_COMPONENT", "euler_to_matrix", "matrix_to_euler", "matrix_to_ur", "tcp_in_m",
                     "translated_in_frame", "ur_to_matrix"), "_geometry"),
    **dict.fromkeys(("Event", "HookSpec", "StationFile", "Vec3"), "_models"),
    **dict.fromkeys(("Operator", "StationRuntime"), "_runtime"),
    **dict.fromkeys(("CalibrationResult", "Compensator", "InstrumentScience", "MeasurementFailed", "PoseMeasurement",
                     "Science"), "_science"),
    "TruthLog": "_truth",
    **dict.fromkeys(("MarkedYaml", "load_marked"), "_yamlmarks"),
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
    "ANGLE_COMPONENT", "CalibrationResult", "Compensator", "ConfigError", "DryRunFailed", "Event",
    "HookSpec", "InputRefused", "InstrumentScience", "MarkedYaml", "MeasurementFailed", "Operator",
    "PoseMeasurement", "ResumeRefused", "RunAborted", "RunError", "RunLocked", "Science", "StateConflict",
    "StationFile",
    "StationRuntime", "TruthLog", "Vec3", "euler_to_matrix", "load_marked", "matrix_to_euler",
    "matrix_to_ur", "read_text_file", "tcp_in_m", "translated_in_frame", "ur_to_matrix",
]
