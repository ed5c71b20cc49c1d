"""A bounded, thread-safe ring of received samples, and the checks that keep bad data out of averages.

The receive thread ``push``es samples; readers wait on a condition for samples by sequence number.
Each sample carries ``defect``: why the feed is *not* contiguous just before it (a counter gap, a
rejected frame, a stall, a reconnection), so a reader that walks a window of consecutive samples
sees every discontinuity inside the window and can refuse to average across it.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from drivers._errors import DeviceFault
from drivers.interferometer._interface import BeamInterrupted, DatumLost, FeedGap, Sample


@dataclass(frozen=True)
class CanSample(Sample):
    """A ``Sample`` with what the CAN feed adds.

    ``timestamp`` is the frame's timestamp as python-can reports it: the device's clock for
    socketcand (sent in the frame), the host's clock at read time for slcan. ``received`` is the
    host's clock when the driver took it. ``displacement`` is NaN whenever it is not a valid
    distance from the current datum (beam not OK, no datum, overrange): a wrong number can never
    be passed on by accident.
    """

    received: float
    datum_set: bool
    signal_low: bool
    overrange: bool
    defect: str  # "" when contiguous with the previous sample, else why not


class FeedBuffer:
    """Ring buffer of ``CanSample`` with sequence numbers (0, 1, 2 ... in arrival order)."""

    def __init__(self, capacity: int, device: str) -> None:
        if capacity < 16:
            raise ValueError(f"ring buffer capacity must be >= 16 samples, got {capacity}")
        self.device = device
        self._capacity = int(capacity)
        self._ring: list[CanSample | None] = [None] * self._capacity
        self._next_seq = 0
        self._last_mono = 0.0
        self._cond = threading.Condition()
        self._failure: Callable[[], Exception | None] = lambda: None

    def set_failure_probe(self, probe: Callable[[], Exception | None]) -> None:
        """``probe()`` returns the error to raise instead of "stale" (e.g. the connection is down)."""
        self._failure = probe

    # --------------------------------------------------------------------------- writer side
    def push(self, sample: CanSample) -> None:
        with self._cond:
            self._ring[self._next_seq % self._capacity] = sample
            self._next_seq += 1
            self._last_mono = time.monotonic()
            self._cond.notify_all()

    def wake(self) -> None:
        """Wake every waiting reader (connection state changed)."""
        with self._cond:
            self._cond.notify_all()

    # --------------------------------------------------------------------------- reader side
    @property
    def next_seq(self) -> int:
        with self._cond:
            return self._next_seq

    def newest(self) -> tuple[CanSample | None, float]:
        """The newest sample and its age in seconds (host clock at arrival); ``(None, inf)`` if none."""
        with self._cond:
            if self._next_seq == 0:
                return None, math.inf
            return self._stored(self._next_seq - 1), time.monotonic() - self._last_mono

    def recent(self, count: int) -> list[CanSample]:
        with self._cond:
            count = max(0, min(int(count), self._next_seq, self._capacity))
            return [self._stored(s) for s in range(self._next_seq - count, self._next_seq)]

    def _stored(self, seq: int) -> CanSample:
        """Sample ``seq``, which the caller knows is still in the ring (held under the lock)."""
        sample = self._ring[seq % self._capacity]
        assert sample is not None, f"sample {seq} was never stored"
        return sample

    def get(self, seq: int, deadline: float, operation: str) -> CanSample:
        """Sample number ``seq``, waiting until ``deadline`` (monotonic) for it to arrive."""
        with self._cond:
            while self._next_seq <= seq:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    failure = self._failure()
                    if failure is not None:
                        raise failure
                    waited = time.monotonic() - self._last_mono if self._next_seq else math.inf
                    raise FeedGap(self.device, operation,
                                  f"no sample received for {waited:.2f} s (feed stalled or not running)")
                self._cond.wait(min(remaining, 0.5))
            if seq < self._next_seq - self._capacity:
                raise FeedGap(self.device, operation,
                              f"reader fell {self._next_seq - seq} samples behind; the ring buffer holds "
                              f"{self._capacity}")
            return self._stored(seq)

    def stream(self, timeout: float, operation: str) -> Iterator[CanSample]:
        """Every sample from now on; ``FeedGap`` when none arrives within ``timeout`` seconds."""
        seq = self.next_seq
        while True:
            yield self.get(seq, time.monotonic() + timeout, operation)
            seq += 1

    def average(self, count: int, deadline: float, sample_timeout: float, operation: str,
                start: int | None = None) -> float:
        """Mean displacement of ``count`` samples from sequence number ``start`` (default: the next
        to arrive), all contiguous, beam OK, datum set. Fails at the first bad sample instead of
        waiting out the window.
        """
        seq = self.next_seq if start is None else start
        total = 0.0
        for index in range(count):
            sample = self.get(seq + index, min(deadline, time.monotonic() + sample_timeout), operation)
            # The first sample's defect concerns what came before the window.
            if index > 0 and sample.defect:
                raise FeedGap(self.device, operation,
                              f"feed not contiguous after {index} of {count} samples: {sample.defect}")
            require_valid(self.device, operation, sample)
            total += sample.displacement
        return total / count


def require_valid(device: str, operation: str, sample: CanSample) -> None:
    """Raise the typed error that explains why ``sample`` carries no valid displacement."""
    if not sample.beam_ok:
        raise BeamInterrupted(device, operation,
                              f"beam not OK at sample {sample.counter} (signal {sample.signal_strength:.2f})")
    if not sample.datum_set:
        raise DatumLost(device, operation,
                        "no valid datum (never set, or the count was lost when the beam broke); call zero()")
    if sample.overrange:
        raise DeviceFault(device, operation, "displacement overrange reported by the head")
