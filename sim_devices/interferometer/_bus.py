"""When a frame the head sends is received on the bus: the timestamps a socketcand daemon forwards.

The real socketcand forwards the receive time the kernel stamped on each frame (``SO_TIMESTAMP``
of the CAN socket), not a time the sender chose. So a frame's timestamp here is made the way the
wire makes it:

- it leaves when the head's clock thread really sends it (its actual time, with the scheduling
  jitter the twin really has, not the ideal due time of the sample);
- it occupies the bus for its length in bits at the bit rate (a standard data frame of ``n``
  bytes is 47 + 8n bits plus 0..(34 + 8n − 1)/4 stuff bits, and 3 bits of interframe space),
  queued behind the frame before it: a reply and the sample after it never share a timestamp;
- the receiving kernel stamps it after its interrupt latency, 5 µs plus an exponential tail with
  mean ``rx_latency`` (capped at 50 times that), drawn from a seeded stream; frames are received
  in bus order, so the stamps never go backwards.
"""

from __future__ import annotations

import threading

import numpy as np

_INTERFRAME_BITS = 3


class CanBusTiming:
    """Receive timestamps (epoch seconds) of the frames put on one CAN bus.

    Parameters
    ----------
    rng : numpy.random.Generator
        Seeded stream for the stuff bits and the receive latency.
    bitrate : float
        Bus bit rate, bit/s.
    rx_latency : float
        Mean of the receive latency's exponential tail, s.
    """

    def __init__(self, rng: np.random.Generator, bitrate: float = 1_000_000.0, rx_latency: float = 20e-6) -> None:
        self._rng = rng
        self.bit_time = 1.0 / float(bitrate)
        self.rx_latency = float(rx_latency)
        self._bus_free = -np.inf  # epoch time at which the bus is idle again
        self._last_stamp = -np.inf
        self._lock = threading.Lock()

    def frame_bits(self, length: int) -> int:
        """Bits a standard data frame of ``length`` bytes occupies on the bus (stuffing drawn)."""
        stuffable = 34 + 8 * length
        return 47 + 8 * length + int(self._rng.integers(0, (stuffable - 1) // 4 + 1)) + _INTERFRAME_BITS

    def receive_time(self, sent: float, length: int) -> float:
        """Epoch time a receiver's kernel stamps on a frame of ``length`` bytes sent at ``sent``."""
        with self._lock:
            start = max(sent, self._bus_free)
            end = start + self.frame_bits(length) * self.bit_time
            self._bus_free = end
            latency = 5e-6 + min(float(self._rng.exponential(self.rx_latency)), 50 * self.rx_latency)
            self._last_stamp = max(end + latency, self._last_stamp + 1e-6)
            return float(self._last_stamp)
