"""A byte-stream relay with fault injection, for twins behind a serial line (pty) or a TCP socket.

Topology for a serial twin::

    twin server ── pty A (slave path opened by the twin) ── relay ── pty B (slave path opened by the driver)

The relay copies requests (host → device) verbatim and splits the device's output into replies with
a *reply framer*; every reply passes the twin's ``FaultPlan`` on its way to the host, so a fault hits
exactly one protocol answer. The same relay core serves a TCP proxy (``relay_sockets``).

Faults taken here (``FaultKind``; params in brackets, defaults in the code):

- ``drop_reply``: the reply is discarded.
- ``delay`` [seconds]: the reply is sent late; later replies queue behind it (a serial device answers
  in order), which leaves stale bytes for a driver that gave up: it must flush before each request.
- ``slow`` [seconds]: like ``delay`` but for every reply while armed (arm with ``count=-1``).
- ``garbage`` [size, mode="prefix"|"replace"]: random bytes before (or instead of) the reply.
- ``truncate``: only the first half of the reply is sent.
- ``bad_crc``: the reply's check bytes are corrupted (``corrupt`` callable; default: flip the last
  two bytes, which are the CRC of a Modbus RTU frame).
- ``stall`` [seconds]: the device produces nothing for a while (replies in the window are lost;
  requests still reach the device).
- ``disconnect`` [seconds]: a serial cable is pulled for a while (nothing passes either way); on a
  socket relay the connection is closed instead.
"""

from __future__ import annotations

import errno
import os
import select
import threading
import time
import tty
from collections import deque
from collections.abc import Callable

import numpy as np

from sim_devices.faults import FaultKind, FaultPlan

ReplyFramer = Callable[[bytes], int]
"""``framer(buffer) -> n``: length of the first complete reply in ``buffer``, 0 if incomplete."""

RELAY_FAULTS = (
    FaultKind.DROP_REPLY,
    FaultKind.DELAY,
    FaultKind.SLOW,
    FaultKind.GARBAGE,
    FaultKind.TRUNCATE,
    FaultKind.BAD_CRC,
    FaultKind.STALL,
    FaultKind.DISCONNECT,
)


def open_raw_pty() -> tuple[int, int, str]:
    """``(master_fd, slave_fd, slave_path)`` of a new pty in raw mode (no echo, no CR/LF mapping)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    return master, slave, os.ttyname(slave)


def chunk_framer(buffer: bytes) -> int:
    """Every chunk read is one reply (for byte streams without a known framing)."""
    return len(buffer)


def line_framer(buffer: bytes) -> int:
    """Replies end with LF; a line ending in ``" \\n"`` continues a multi-line answer (PI GCS 2.0)."""
    start = 0
    while (index := buffer.find(b"\n", start)) >= 0:
        if index == 0 or buffer[index - 1 : index] != b" ":
            return index + 1
        start = index + 1
    return 0


def modbus_rtu_reply_framer(buffer: bytes) -> int:
    """Length of a Modbus RTU *response* frame at the start of ``buffer`` (0 if incomplete)."""
    if len(buffer) < 2:
        return 0
    function = buffer[1]
    if function & 0x80:
        need = 5
    elif function in (1, 2, 3, 4, 23):
        if len(buffer) < 3:
            return 0
        need = 3 + buffer[2] + 2
    elif function in (5, 6, 15, 16):
        need = 8
    else:  # unknown function: pass whatever arrived
        return len(buffer)
    return need if len(buffer) >= need else 0


def modbus_tcp_reply_framer(buffer: bytes) -> int:
    """Length of a Modbus TCP (MBAP) frame at the start of ``buffer`` (0 if incomplete)."""
    if len(buffer) < 6:
        return 0
    need = 6 + int.from_bytes(buffer[4:6], "big")
    return need if len(buffer) >= need else 0


def flip_last_two_bytes(reply: bytes) -> bytes:
    return reply[:-2] + bytes(b ^ 0xA5 for b in reply[-2:]) if len(reply) >= 2 else bytes([reply[0] ^ 0xA5])


class FaultyRelay:
    """Relay bytes between a device fd and a host fd in a thread, injecting the plan's faults.

    Parameters
    ----------
    device_fd, host_fd : int
        File descriptors (pty masters or connected sockets). The relay does not own them unless
        ``owned_fds`` lists them; those it closes on ``stop``.
    faults : FaultPlan
        Where faults are taken from (only the kinds in ``RELAY_FAULTS``).
    framer : callable
        Splits the device's output into replies (see ``ReplyFramer``).
    corrupt : callable
        What ``bad_crc`` does to a reply.
    hang_up_on_disconnect : bool
        True for sockets (``disconnect`` closes the relay); False for serial lines (``disconnect``
        silences the line for ``seconds``).
    seed : int
        Seeds the garbage bytes.
    """

    def __init__(
        self,
        device_fd: int,
        host_fd: int,
        faults: FaultPlan,
        *,
        framer: ReplyFramer = chunk_framer,
        corrupt: Callable[[bytes], bytes] = flip_last_two_bytes,
        hang_up_on_disconnect: bool = False,
        owned_fds: tuple[int, ...] = (),
        seed: int = 0,
        name: str = "relay",
        incomplete_flush_after: float = 0.25,
    ) -> None:
        self.device_fd = device_fd
        self.host_fd = host_fd
        self.faults = faults
        self.framer = framer
        self.corrupt = corrupt
        self.hang_up_on_disconnect = hang_up_on_disconnect
        self.name = name
        self.incomplete_flush_after = incomplete_flush_after
        self._owned = list(owned_fds)
        self._rng = np.random.default_rng(seed)
        self._wake_r, self._wake_w = os.pipe()
        self._stop = threading.Event()
        self._pending: deque[tuple[float, bytes]] = deque()  # (due time, bytes) towards the host
        self._from_device = b""
        self._from_device_since = 0.0
        self._silent_until = 0.0  # disconnect: nothing passes
        self._mute_until = 0.0  # stall: the device sends nothing
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.closed = threading.Event()  # set when the relay ended (stop, hang-up, peer closed)
        self.on_close: Callable[[], None] | None = None

    def start(self) -> FaultyRelay:
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout)
        self._close_fds()

    def _close_fds(self) -> None:
        for fd in [*self._owned, self._wake_r, self._wake_w]:
            try:
                os.close(fd)
            except OSError:
                pass
        self._owned = []
        self._wake_r = self._wake_w = -1

    # ----------------------------------------------------------------------------- the loop
    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                wait = 0.2
                if self._pending:
                    wait = min(wait, max(0.0, self._pending[0][0] - now))
                if self._from_device:
                    wait = min(wait, max(0.0, self._from_device_since + self.incomplete_flush_after - now))
                readable, _, _ = select.select([self.device_fd, self.host_fd, self._wake_r], [], [], wait)
                if self._wake_r in readable:
                    break
                if self.host_fd in readable and not self._pump_requests():
                    break
                if self.device_fd in readable and not self._pump_replies():
                    break
                self._flush_incomplete()
                if not self._send_due():
                    break
        finally:
            self.closed.set()
            if self.on_close is not None:
                self.on_close()

    def _read(self, fd: int) -> bytes | None:
        """Bytes from ``fd``; None when the peer is gone."""
        try:
            data = os.read(fd, 65536)
        except BlockingIOError:
            return b""
        except OSError as exc:
            if exc.errno == errno.EIO:  # pty: the other side has no open slave right now
                time.sleep(0.01)
                return b""
            return None
        return data if data else None

    def _pump_requests(self) -> bool:
        data = self._read(self.host_fd)
        if data is None:
            return False
        if data and time.monotonic() >= self._silent_until:
            self._write(self.device_fd, data)
        return True

    def _pump_replies(self) -> bool:
        data = self._read(self.device_fd)
        if data is None:
            return False
        if not data:
            return True
        if not self._from_device:
            self._from_device_since = time.monotonic()
        self._from_device += data
        while self._from_device and (length := self.framer(self._from_device)) > 0:
            reply, self._from_device = self._from_device[:length], self._from_device[length:]
            self._from_device_since = time.monotonic()
            if not self._reply(reply):
                return False
        return True

    def _flush_incomplete(self) -> None:
        """A partial reply that never completes is passed on as it is (the driver must cope)."""
        if self._from_device and time.monotonic() - self._from_device_since >= self.incomplete_flush_after:
            reply, self._from_device = self._from_device, b""
            self._reply(reply)

    def _reply(self, reply: bytes) -> bool:
        """Apply at most one transport fault to ``reply`` and queue it; False to hang up."""
        now = time.monotonic()
        if now < self._silent_until or now < self._mute_until:
            return True
        due = now
        fault = self.faults.take(*RELAY_FAULTS)
        if fault is not None:
            kind, params = fault.kind, fault.params
            if kind is FaultKind.DROP_REPLY:
                return True
            if kind is FaultKind.DELAY or kind is FaultKind.SLOW:
                due = now + float(params.get("seconds", 0.5))
            elif kind is FaultKind.GARBAGE:
                size = int(params.get("size", 8))
                junk = bytes(self._rng.integers(0x80, 0x100, size, dtype=np.uint8))  # never a LF
                reply = junk if params.get("mode", "prefix") == "replace" else junk + reply
            elif kind is FaultKind.TRUNCATE:
                reply = reply[: max(1, len(reply) // 2)] if len(reply) > 1 else b""
            elif kind is FaultKind.BAD_CRC:
                reply = self.corrupt(reply)
            elif kind is FaultKind.STALL:
                self._mute_until = now + float(params.get("seconds", 1.0))
                return True
            elif kind is FaultKind.DISCONNECT:
                if self.hang_up_on_disconnect:
                    return False
                self._silent_until = now + float(params.get("seconds", 1.0))
                self._pending.clear()
                return True
        if self._pending:
            due = max(due, self._pending[-1][0])  # replies leave in order
        if reply:
            self._pending.append((due, reply))
        return True

    def _send_due(self) -> bool:
        now = time.monotonic()
        while self._pending and self._pending[0][0] <= now:
            _, reply = self._pending.popleft()
            if time.monotonic() < self._silent_until:
                continue
            if not self._write(self.host_fd, reply):
                return False
        return True

    def _write(self, fd: int, data: bytes) -> bool:
        view = memoryview(data)
        deadline = time.monotonic() + 2.0
        while view:
            try:
                written = os.write(fd, view)
            except BlockingIOError:
                if time.monotonic() > deadline:
                    return True  # nobody reads: drop, like a full UART buffer
                time.sleep(0.001)
                continue
            except OSError:
                return False
            view = view[written:]
        return True


class PtyRelay:
    """Two raw ptys and a ``FaultyRelay`` between them.

    ``device_path`` is opened by the twin's server, ``host_path`` by the driver (like ``/dev/ttyUSB0``).
    """

    def __init__(self, faults: FaultPlan, *, framer: ReplyFramer = chunk_framer,
                 corrupt: Callable[[bytes], bytes] = flip_last_two_bytes, seed: int = 0,
                 name: str = "pty relay") -> None:
        device_master, device_slave, self.device_path = open_raw_pty()
        host_master, host_slave, self.host_path = open_raw_pty()
        for fd in (device_master, host_master):
            os.set_blocking(fd, False)
        # Holding both slaves open keeps the masters readable without EIO while no one has the path open.
        self.relay = FaultyRelay(
            device_master, host_master, faults, framer=framer, corrupt=corrupt, seed=seed, name=name,
            owned_fds=(device_master, device_slave, host_master, host_slave),
        )

    def start(self) -> PtyRelay:
        self.relay.start()
        return self

    def stop(self) -> None:
        self.relay.stop()
