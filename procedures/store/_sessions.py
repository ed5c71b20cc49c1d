"""The test conditions of one session of a run: a run-level record, written once per session.

Every session of a run (``instrument run``, then each ``instrument resume``) of a kind that records its
test conditions reads them at its start: who the robot is (its controller's answer), the payload set on it,
the warm-up, the operator. The store keeps them in the ``session_conditions`` table (schema version 6),
committed in the same transaction as the session's first sample, so a record always describes data that
exists. Runs stored before version 6 carried the record in the first sample's ``reference["session"]``;
``RunStore.sessions`` reads both.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class SessionConditions:
    """The test conditions one session of a run started under (SI).

    started : host time the session's conditions were read (s since the epoch)
    robot : the controller's identity (``manufacturer``, ``model``, ``serial_number``, ``controller_version``,
        ``source``), or ``{"error", "source"}`` when it did not answer
    payload : ``mass_kg``, ``cog_m`` (flange frame, m), ``set_on_robot``
    operator : ``name`` and where it came from (``source``)
    warm_up : ``mode`` (declared, run), ``duration_s``, and for a warm-up the instrument ran ``ran_s`` and
        ``moves``; None for a kind that records none
    """

    started: float
    robot: Mapping[str, Any]
    payload: Mapping[str, Any]
    operator: Mapping[str, Any]
    warm_up: Mapping[str, Any] | None = None

    def to_stored(self) -> dict[str, Any]:
        """The record as stored and as the results' ``test_conditions.sessions`` list it (docs/results.md)."""
        out: dict[str, Any] = {"started": self.started, "robot": dict(self.robot), "payload": dict(self.payload)}
        if self.warm_up is not None:
            out["warm_up"] = dict(self.warm_up)
        out["operator"] = dict(self.operator)
        return out

    @classmethod
    def from_stored(cls, data: Mapping[str, Any]) -> SessionConditions:
        warm_up = data.get("warm_up")
        return cls(started=float(data.get("started") or 0.0), robot=dict(data.get("robot") or {}),
                   payload=dict(data.get("payload") or {}), operator=dict(data.get("operator") or {}),
                   warm_up=None if warm_up is None else dict(warm_up))
