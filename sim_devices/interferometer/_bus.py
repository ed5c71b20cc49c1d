"""When a frame the head sends is received on the bus: the timestamps a socketcand daemon forwards.

The real socketcand forwards the receive time the kernel stamped on each frame (``SO_TIMESTAMP``
of its CAN socket), not a time the sender chose. Here the moment the twin hands a frame to its
transports stands for the moment the socketcand host's CAN controller has received it, so:

- a sample's frame goes on the bus at the sample's due time on the head's clock (the clock
  thread sends the samples due in batches of a few milliseconds, each with its own time; a reply
  goes out when its command is executed), and its timestamp is that time plus the receiving
  kernel's interrupt latency: 5 µs and an exponential tail of mean ``rx_latency`` (capped at 50
  times that), drawn from a seeded stream;
- frames cannot be closer together than the bus can carry them: a standard data frame of ``n``
  bytes takes 47 + 8n bits plus 0..(34 + 8n − 1)/4 stuff bits and 3 bits of interframe space
  (114..138 µs for 8 bytes at 1 Mbit/s), so a reply and the sample sent right after it, or a
  burst of samples a late clock thread catches up with, are spread out as the bus spreads them;
- frames are received in bus order: the stamps never go backwards.

A frame is handed over up to a batch (10 ms) after its stamp, as a socketcand daemon forwards the
frames its kernel queued; a frame queued behind others on the bus gets a stamp a little later
(by the bus time of the frames before it).
"""

from __future__ import annotations

import threading

import numpy as np

_INTERFRAME_BITS = 3
_BLOCK = 1024  # draws per refill


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
        self._received = -np.inf  # when the previous frame was received
        self._last_stamp = -np.inf
        self._lock = threading.Lock()
        # Drawn in blocks: one numpy call per scalar costs more than the rest of a frame's timing.
        self._uniform: list[float] = []
        self._latency: list[float] = []

    def frame_bits(self, length: int) -> int:
        """Bits a standard data frame of ``length`` bytes occupies on the bus (stuffing drawn)."""
        stuffable = 34 + 8 * length
        if not self._uniform:
            self._uniform = self._rng.random(_BLOCK).tolist()
        stuff = int(self._uniform.pop() * ((stuffable - 1) // 4 + 1))  # uniform on 0..(stuffable - 1) // 4
        return 47 + 8 * length + stuff + _INTERFRAME_BITS

    def receive_time(self, sent: float, length: int) -> float:
        """Kernel timestamp (epoch s) of a frame of ``length`` bytes handed over at ``sent`` (epoch s)."""
        with self._lock:
            received = max(sent, self._received + self.frame_bits(length) * self.bit_time)
            self._received = received
            if not self._latency:
                tail = self._rng.exponential(self.rx_latency, _BLOCK)
                self._latency = (5e-6 + np.minimum(tail, 50 * self.rx_latency)).tolist()
            self._last_stamp = max(received + self._latency.pop(), self._last_stamp + 1e-6)
            return float(self._last_stamp)
