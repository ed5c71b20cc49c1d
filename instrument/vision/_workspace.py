"""Scratch arrays that the vision reuses from one call to the next (``VisionWorkspace``)."""

from __future__ import annotations

import math

import numpy as np

HEADROOM = 1.25  # a buffer grows to this multiple of the request, so slowly growing sizes do not reallocate
MAX_CACHED = 64  # small derived index arrays kept per workspace (a stream sees a handful of layouts)


class VisionWorkspace:
    """Scratch memory for ``locate_cross`` / ``locate_crosses``, reused across calls.

    One trigger of three 5 MP frames needs several MB of temporaries (the bands across the
    stripes, the IGCF windows, their float32 moments). Allocated afresh on every call, that
    memory can go back to the operating system between triggers and be page-faulted in again on
    the next one (glibc does so until the process has freed one big block): measured on the
    development VM at 1582 page faults and 2.8 ms of system time per trigger before, 248 and
    0.47 ms with a workspace. A stream (``instrument.stream.PoseTracker``) therefore keeps one
    workspace and passes it to every call.

    The functions stay pure in effect: no result ever refers to a workspace buffer, and a call
    with a fresh workspace gives the same result as one with a used workspace. A workspace is
    not thread-safe: one per thread (or per stream).
    """

    def __init__(self) -> None:
        self._buffers: dict[str, np.ndarray] = {}
        self._cache: dict[tuple, object] = {}

    def array(self, name: str, shape: tuple[int, ...], dtype) -> np.ndarray:
        """A C-contiguous array of ``shape`` and ``dtype`` whose contents are undefined.

        Successive requests under one ``name`` share memory: the array of the previous request
        under that name is overwritten by the users of the next one.
        """
        dtype = np.dtype(dtype)
        size = math.prod(shape)
        buffer = self._buffers.get(name)
        if buffer is None or buffer.dtype != dtype or buffer.size < size:
            buffer = np.empty(max(int(size * HEADROOM), 1), dtype)
            self._buffers[name] = buffer
        return buffer[:size].reshape(shape)

    def cached(self, key: tuple, make):
        """``make()`` the first time ``key`` is asked for, the stored value afterwards (a small
        array derived from the layout only, e.g. segment bounds; never modify it)."""
        value = self._cache.get(key)
        if value is None:
            if len(self._cache) >= MAX_CACHED:
                self._cache.clear()
            value = self._cache[key] = make()
        return value

    @property
    def nbytes(self) -> int:
        """Bytes held by the scratch buffers."""
        return sum(b.nbytes for b in self._buffers.values())
