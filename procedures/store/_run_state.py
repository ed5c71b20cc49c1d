"""The states of a run, as one Enum.

QUEUED → RUNNING → (PAUSED ⇄ RUNNING) → FINISHED | FAILED | ABORTED. The values are the strings
the run store and every JSON event have always used, so stored runs read back unchanged.
"""

from __future__ import annotations

from enum import StrEnum


class RunState(StrEnum):
    """One run's state; a ``str``, so it compares equal to and serialises as its stored value."""

    QUEUED = "QUEUED"
    RUNNING = "RUNNING"
    PAUSED = "PAUSED"
    FINISHED = "FINISHED"
    FAILED = "FAILED"
    ABORTED = "ABORTED"

    @property
    def resumable(self) -> bool:
        """Whether ``instrument resume`` may continue a run in this state (FINISHED and ABORTED are final)."""
        return self in _RESUMABLE

    @property
    def ended(self) -> bool:
        """Whether the run stopped for good or for now with an outcome (it gets a ``finished`` time)."""
        return self in _EXIT_STATUS

    @property
    def exit_status(self) -> str | None:
        """``success``, ``fail`` or ``abort`` for an ended run, else None (stored beside the state)."""
        return _EXIT_STATUS.get(self)


_RESUMABLE = frozenset({RunState.QUEUED, RunState.RUNNING, RunState.PAUSED, RunState.FAILED})
_EXIT_STATUS = {RunState.FINISHED: "success", RunState.FAILED: "fail", RunState.ABORTED: "abort"}
RESUMABLE_STATES = tuple(state for state in RunState if state.resumable)
