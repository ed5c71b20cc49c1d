"""Procedure kinds, grouped by family, each implementing ``ProcedureKind``; and their registry.

What it offers: ``KINDS`` (every kind by its ``procedure:`` name) and ``kind_of``; the Protocol and the
types that cross it (``Step``, ``StepContext``, ``PoseReading``, ``Reading``, ``AnalysisContext``,
``Analysis``, the set-ups, ``MotionParameters``, ``ProcedureBase``); a move's pose stream
(``StreamRecord``); the export's normalised results (``normalised_results``); and the helpers several
families share (``pose_directions``, ``environment_summary``, ``scale_uncertainty``).

The families: ``procedures.kinds.iso`` (pose repeatability and accuracy), ``procedures.kinds.calibration``
(displacement and angle calibrations), ``procedures.kinds.dynamic`` (stabilisation and paths, measured in
motion). A kind never imports the engine, the report or the faces (the import contract is a test).

Adding a kind: a module in a family (or a new family) with its parameter model, its procedure-file
model with ``procedure: Literal["<name>"]`` and a class implementing ``ProcedureKind``; add it to
``_REGISTERED`` below and regenerate the schemas (``python -m procedures.engine.write_schemas``). The engine,
the loader, the report and the faces find it here and nowhere else.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

from procedures.kinds import calibration, dynamic, iso
from procedures.kinds._approach import pose_directions
from procedures.kinds._environment import environment_summary
from procedures.kinds._export import normalised_results
from procedures.kinds._parameters import AxisName, MotionParameters, ProcedureBase, retry_wait
from procedures.kinds._protocol import (
    RESULTS_VERSION,
    Analysis,
    AnalysisContext,
    DeviceRole,
    PoseReading,
    ProcedureKind,
    Reading,
    ResultShape,
    Step,
    StepContext,
)
from procedures.kinds._references import scale_uncertainty
from procedures.kinds._setups import (
    RESTING_SETUP,
    InterferometerAligned,
    OprOnRobot,
    OprOnTable,
    Setup,
    SetupCell,
)
from procedures.kinds._stream import COLUMNS, StreamRecord

_REGISTERED: tuple[ProcedureKind[Any], ...] = (
    calibration.DISPLACEMENT,
    calibration.ANGLE,
    iso.REPEATABILITY,
    dynamic.STABILISATION,
    dynamic.PATH,
)
_KINDS: dict[str, ProcedureKind[Any]] = {kind.name: kind for kind in _REGISTERED}
KINDS: Mapping[str, ProcedureKind[Any]] = MappingProxyType(_KINDS)
"""Every kind by its ``procedure:`` name, in registration order (read-only)."""


def register(kind: ProcedureKind[Any]) -> None:
    """Add a kind defined elsewhere (a plug-in, a test) to ``KINDS``; its name must be new."""
    if kind.name in _KINDS:
        raise ValueError(f"a procedure kind named {kind.name!r} is already registered")
    _KINDS[kind.name] = kind


def unregister(name: str) -> None:
    """Remove a kind ``register`` added (the built-in kinds stay)."""
    if any(kind.name == name for kind in _REGISTERED):
        raise ValueError(f"{name!r} is a built-in procedure kind")
    _KINDS.pop(name, None)


def kind_of(procedure: ProcedureBase) -> ProcedureKind[Any]:
    """The kind that runs a validated procedure file."""
    return KINDS[procedure.procedure]


__all__ = [
    "COLUMNS",
    "KINDS",
    "RESULTS_VERSION",
    "RESTING_SETUP",
    "Analysis",
    "AnalysisContext",
    "AxisName",
    "DeviceRole",
    "InterferometerAligned",
    "MotionParameters",
    "OprOnRobot",
    "OprOnTable",
    "PoseReading",
    "ProcedureBase",
    "ProcedureKind",
    "Reading",
    "ResultShape",
    "Setup",
    "SetupCell",
    "Step",
    "StepContext",
    "StreamRecord",
    "environment_summary",
    "kind_of",
    "normalised_results",
    "pose_directions",
    "register",
    "retry_wait",
    "scale_uncertainty",
    "unregister",
]
