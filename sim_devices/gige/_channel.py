"""The twin's stream channel: a frame cut into GVSP packets, sent, and kept for packet resend.

A real camera sends each block (leader, payload packets, trailer) to the stream destination the
host wrote (``GevSCDA``:``GevSCPHostPort``), and keeps the last blocks in its memory so that a
PACKETRESEND from the host can be served. Here the last ``keep`` blocks are kept; a resend of one
that is gone is answered with a PACKET_UNAVAILABLE packet per id, as the standard asks.

Fault: ``drop(fraction, count, seed)`` — the first transmission of a payload packet is skipped
with probability ``fraction`` (seeded; at most ``count`` packets, None: no limit). The packet stays
in the resend memory, so a client that asks for it gets it: what a lossy link with a resend-capable
camera looks like. Leaders and trailers are never dropped (a client needs the leader to know the
block; losing one is a lost frame, which ``unresponsive`` covers).
"""

from __future__ import annotations

import socket
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from sim_devices.gige import _wire as w

SEND_BUFFER = 8 << 20  # bytes of socket send buffer: a few full frames


@dataclass
class ChannelStats:
    """Blocks and packets sent, payload packets dropped on purpose, packets resent, resends refused."""

    blocks: int = 0
    packets: int = 0
    dropped: int = 0
    resent: int = 0
    unavailable: int = 0
    resend_requests: int = 0
    no_destination: int = 0
    send_errors: int = 0


class StreamChannel:
    """GVSP sender of one camera (see the module docstring).

    Parameters
    ----------
    host : str
        The camera's address: the stream packets' source.
    keep : int
        Blocks kept for resend.
    """

    def __init__(self, host: str, keep: int = 8) -> None:
        self.socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.socket.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        except OSError:
            pass  # the system's limit: the default buffer still works, only sooner full
        self.socket.bind((host, 0))
        self.source_port = int(self.socket.getsockname()[1])
        self.keep = int(keep)
        self.stats = ChannelStats()
        self._blocks: OrderedDict[int, tuple[tuple[str, int], list[bytes]]] = OrderedDict()
        self._lock = threading.Lock()
        self._drop_fraction = 0.0
        self._drop_left: int | None = None
        self._drop_rng = np.random.default_rng(0)

    def close(self) -> None:
        self.socket.close()

    def drop(self, fraction: float, count: int | None = None, seed: int = 0) -> None:
        """Skip the first transmission of payload packets with probability ``fraction`` (0 ends it)."""
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"drop fraction must be in [0, 1], got {fraction}")
        with self._lock:
            self._drop_fraction = float(fraction)
            self._drop_left = None if count is None else int(count)
            self._drop_rng = np.random.default_rng(seed)

    def _dropping(self) -> bool:
        if self._drop_fraction <= 0.0 or self._drop_left == 0:
            return False
        if self._drop_rng.random() >= self._drop_fraction:
            return False
        if self._drop_left is not None:
            self._drop_left -= 1
        return True

    def send_block(self, destination: tuple[str, int], block_id: int, timestamp: int, pixel_format: int,
                   roi: tuple[int, int, int, int], data: bytes, packet_size: int) -> None:
        """Cut ``data`` (the image bytes) into packets of ``packet_size`` datagram bytes and send them."""
        if destination[1] == 0:
            with self._lock:
                self.stats.no_destination += 1
            return
        chunk = packet_size - w.GVSP_DATAGRAM_OVERHEAD
        offset_x, offset_y, width, height = roi
        packets = [w.gvsp_leader(block_id, timestamp, pixel_format, width, height, offset_x, offset_y)]
        view = memoryview(data)
        packets += [w.gvsp_payload(block_id, i + 1, view[start:start + chunk])
                    for i, start in enumerate(range(0, len(data), chunk))]
        packets.append(w.gvsp_trailer(block_id, len(packets), height))
        with self._lock:
            self._blocks[block_id] = (destination, packets)
            self._blocks.move_to_end(block_id)
            while len(self._blocks) > self.keep:
                self._blocks.popitem(last=False)
            skipped = {i for i in range(1, len(packets) - 1) if self._dropping()}
            self.stats.blocks += 1
            self.stats.dropped += len(skipped)
        sent = 0
        for i, packet in enumerate(packets):
            if i in skipped:
                continue
            sent += self._send(packet, destination)
        with self._lock:
            self.stats.packets += sent

    def _send(self, packet: bytes, destination: tuple[str, int]) -> int:
        try:
            self.socket.sendto(packet, destination)
            return 1
        except OSError:  # a full buffer or a vanished host: the packet is lost, as on a wire
            with self._lock:
                self.stats.send_errors += 1
            return 0

    def resend(self, block_id: int, first: int, last: int, destination: tuple[str, int]) -> None:
        """Serve a PACKETRESEND: packets ``first``…``last`` of ``block_id`` again to where the block
        went, or, for a block no longer kept, one PACKET_UNAVAILABLE packet per id to ``destination``
        (the current stream destination)."""
        with self._lock:
            self.stats.resend_requests += 1
            kept = self._blocks.get(block_id)
        if kept is None:
            if destination[1] != 0:
                for packet_id in range(first, min(last, first + 64) + 1):  # a bounded answer to any range
                    self._send(w.gvsp_unavailable(block_id, packet_id), destination)
                    with self._lock:
                        self.stats.unavailable += 1
            return
        destination, packets = kept
        last = min(last, len(packets) - 1)
        for packet_id in range(first, last + 1):
            if 0 <= packet_id < len(packets):
                self._send(packets[packet_id], destination)
                with self._lock:
                    self.stats.resent += 1
            else:
                self._send(w.gvsp_unavailable(block_id, packet_id), destination)
                with self._lock:
                    self.stats.unavailable += 1
