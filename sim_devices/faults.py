"""One way to inject faults into every twin.

A twin owns a ``FaultPlan``; tests (or the cell's control API) arm faults on it; the twin's
transport takes them where they belong (the pty relay drops or garbles a reply, the Modbus action
answers an exception code, the CAN stream breaks the beam, the robot enters protective stop).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any


class FaultKind(StrEnum):
    DROP_REPLY = "drop_reply"  # the request is read, no answer is sent
    DELAY = "delay"  # the answer comes late (params: seconds)
    GARBAGE = "garbage"  # random bytes instead of (or before) the answer
    TRUNCATE = "truncate"  # only part of the answer is sent
    BAD_CRC = "bad_crc"  # the answer's checksum is wrong
    EXCEPTION = "exception"  # a protocol-level error answer (params: code)
    DISCONNECT = "disconnect"  # the connection is closed by the device
    BEAM_BREAK = "beam_break"  # interferometer: beam lost (params: seconds)
    STALL = "stall"  # the device stops producing data (params: seconds)
    PROTECTIVE_STOP = "protective_stop"  # robot
    EMERGENCY_STOP = "emergency_stop"  # robot
    PROGRAM_STOPPED = "program_stopped"  # robot
    SLOW = "slow"  # every answer is slowed (params: seconds)


def fault_kind(kind: FaultKind | str) -> FaultKind:
    """``kind`` as a ``FaultKind``; a ValueError naming the known kinds if it is none of them."""
    try:
        return FaultKind(kind)
    except ValueError:
        known = ", ".join(k.value for k in FaultKind)
        raise ValueError(f"unknown fault kind {kind!r}; expected one of {known}") from None


@dataclass
class ArmedFault:
    kind: FaultKind
    remaining: int  # how many times it fires; -1 = until cleared
    params: dict[str, Any] = field(default_factory=dict)


class FaultPlan:
    """Thread-safe list of armed faults. ``take`` consumes one firing of a matching fault."""

    def __init__(self) -> None:
        self._armed: list[ArmedFault] = []
        self._fired: list[tuple[FaultKind, dict[str, Any]]] = []
        self._lock = threading.Lock()

    def arm(self, kind: FaultKind | str, count: int = 1, **params: Any) -> None:
        """Arm ``kind`` to fire ``count`` times (-1: until cleared)."""
        kind = fault_kind(kind)
        if count == 0 or count < -1:
            raise ValueError(f"fault count must be positive or -1, got {count}")
        with self._lock:
            self._armed.append(ArmedFault(kind, count, dict(params)))

    def take(self, *kinds: FaultKind | str) -> ArmedFault | None:
        """Consume one firing of the first armed fault among ``kinds``; None when none is armed."""
        wanted = {fault_kind(k) for k in kinds}
        with self._lock:
            for armed in self._armed:
                if armed.kind in wanted:
                    if armed.remaining > 0:
                        armed.remaining -= 1
                        if armed.remaining == 0:
                            self._armed.remove(armed)
                    self._fired.append((armed.kind, dict(armed.params)))
                    return ArmedFault(armed.kind, armed.remaining, dict(armed.params))
        return None

    def peek(self, *kinds: FaultKind | str) -> ArmedFault | None:
        """The first armed fault among ``kinds`` without consuming it."""
        wanted = {fault_kind(k) for k in kinds}
        with self._lock:
            for armed in self._armed:
                if armed.kind in wanted:
                    return ArmedFault(armed.kind, armed.remaining, dict(armed.params))
        return None

    def clear(self, *kinds: FaultKind | str) -> None:
        """Disarm ``kinds`` (all faults when none is given)."""
        wanted = {fault_kind(k) for k in kinds}
        with self._lock:
            self._armed = [a for a in self._armed if wanted and a.kind not in wanted]

    def armed(self) -> list[ArmedFault]:
        with self._lock:
            return [ArmedFault(a.kind, a.remaining, dict(a.params)) for a in self._armed]

    def fired(self) -> list[tuple[FaultKind, dict[str, Any]]]:
        """Every firing so far, oldest first (for tests that check a fault really happened)."""
        with self._lock:
            return list(self._fired)
