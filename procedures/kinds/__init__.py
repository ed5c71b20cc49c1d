"""Procedure kinds: one module per kind, each implementing ``ProcedureKind``, and their registry.

Adding a kind: write ``procedures/kinds/<name>.py`` (its parameter model, its procedure-file
model with ``procedure: Literal["<name>"]``, and a class implementing ``ProcedureKind``), add its
``KIND`` to ``_REGISTERED`` below, and regenerate the schemas (``python -m procedures._loading``).
The engine, the loader, the report and the CLI find it here and nowhere else.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

from procedures.kinds import (
    angle_calibration,
    displacement_calibration,
    iso9283_path,
    iso9283_repeatability,
    iso9283_stabilisation,
)
from procedures.kinds._parameters import AxisName, MotionParameters, ProcedureBase, retry_wait
from procedures.kinds._protocol import (
    Analysis,
    AnalysisContext,
    DeviceRole,
    PoseReading,
    ProcedureKind,
    Reading,
    Step,
    StepContext,
)
from procedures.kinds._setups import (
    RESTING_SETUP,
    InterferometerAligned,
    OprOnRobot,
    OprOnTable,
    Setup,
    SetupCell,
)

_REGISTERED: tuple[ProcedureKind[Any], ...] = (
    displacement_calibration.KIND,
    angle_calibration.KIND,
    iso9283_repeatability.KIND,
    iso9283_stabilisation.KIND,
    iso9283_path.KIND,
)
_KINDS: dict[str, ProcedureKind[Any]] = {kind.name: kind for kind in _REGISTERED}
KINDS: Mapping[str, ProcedureKind[Any]] = MappingProxyType(_KINDS)
"""Every kind by its ``procedure:`` name, in registration order (read-only)."""


def kind_of(procedure: ProcedureBase) -> ProcedureKind[Any]:
    """The kind that runs a validated procedure file."""
    return KINDS[procedure.procedure]


__all__ = [
    "KINDS",
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
    "Setup",
    "SetupCell",
    "Step",
    "StepContext",
    "kind_of",
    "retry_wait",
]
