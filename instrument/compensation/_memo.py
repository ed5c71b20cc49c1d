"""Memo of pure array functions: the held-out evaluation fits every method on the same folds.

``calibrate()`` refits each of its methods on every leave-one-point-out and leave-one-group-out
fold; the group alignment and the ripple search depend only on the fold's data, so each is
computed once per fold and shared by the methods. A memo entry is keyed by a digest of the
arguments' bytes, so a hit returns what the same call computed (the results are frozen
dataclasses; their arrays are made read-only so no caller can change what another one gets).
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import fields, is_dataclass
from typing import Any, Generic, TypeVar

import numpy as np

T = TypeVar("T")


def digest(*parts: Any) -> bytes:
    """BLAKE2 digest of arrays (dtype, shape, bytes) and plain values (their repr)."""
    h = hashlib.blake2b(digest_size=20)
    for part in parts:
        if isinstance(part, np.ndarray):
            array = np.ascontiguousarray(part)
            h.update(f"{array.dtype.str}{array.shape}".encode())
            h.update(array.tobytes())
        else:
            h.update(repr(part).encode())
        h.update(b"|")
    return h.digest()


def _freeze(value: Any) -> None:
    if isinstance(value, np.ndarray):
        value.flags.writeable = False
    elif is_dataclass(value) and not isinstance(value, type):
        for f in fields(value):
            _freeze(getattr(value, f.name))


class Memo(Generic[T]):
    """Least-recently-used memo of at most ``size`` results (thread-safe)."""

    def __init__(self, size: int = 64):
        self.size = size
        self._entries: OrderedDict[bytes, T] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: bytes, compute: Callable[[], T]) -> T:
        with self._lock:
            if key in self._entries:
                self._entries.move_to_end(key)
                return self._entries[key]
        value = compute()
        _freeze(value)
        with self._lock:
            self._entries[key] = value
            while len(self._entries) > self.size:
                self._entries.popitem(last=False)
        return value
