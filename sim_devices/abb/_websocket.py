"""The server side of RFC 6455 as RWS 1.0 uses it: the upgrade of ``GET /poll/<group>`` (subprotocol
``robapi2_subscription``) and unmasked text frames carrying the XHTML events, a reader that
answers pings and closes, and a writer thread per connection so a slow subscriber never blocks
the controller.
"""

from __future__ import annotations

import base64
import hashlib
import queue
import socket
import struct
import threading
from typing import BinaryIO

GUID = "258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
SUBPROTOCOL = "robapi2_subscription"
OP_TEXT, OP_CLOSE, OP_PING, OP_PONG = 0x1, 0x8, 0x9, 0xA


def accept_key(key: str) -> str:
    return base64.b64encode(hashlib.sha1((key.strip() + GUID).encode()).digest()).decode()


def frame(opcode: int, payload: bytes) -> bytes:
    """One final, unmasked frame (a server never masks)."""
    n = len(payload)
    if n < 126:
        head = struct.pack("!BB", 0x80 | opcode, n)
    elif n < 1 << 16:
        head = struct.pack("!BBH", 0x80 | opcode, 126, n)
    else:
        head = struct.pack("!BBQ", 0x80 | opcode, 127, n)
    return head + payload


def read_frame(stream: BinaryIO) -> tuple[int, bytes] | None:
    """(opcode, payload) of the next frame from a client (masked), or None at the end of the stream."""
    head = stream.read(2)
    if len(head) < 2:
        return None
    opcode, length = head[0] & 0x0F, head[1] & 0x7F
    if length == 126:
        length = struct.unpack("!H", stream.read(2))[0]
    elif length == 127:
        length = struct.unpack("!Q", stream.read(8))[0]
    mask = stream.read(4) if head[1] & 0x80 else b"\0\0\0\0"
    data = stream.read(length)
    if len(data) < length:
        return None
    return opcode, bytes(b ^ mask[i % 4] for i, b in enumerate(data))


class WebSocketConnection:
    """One upgraded connection: ``send_text`` queues an event; ``serve`` reads until it closes."""

    def __init__(self, sock: socket.socket, stream: BinaryIO) -> None:
        self.sock = sock
        self.stream = stream
        self.closed = threading.Event()
        self._out: queue.Queue[bytes | None] = queue.Queue(maxsize=1000)
        self._writer = threading.Thread(target=self._write, name="rws-websocket-writer", daemon=True)
        self._writer.start()

    def send_text(self, text: str) -> None:
        if self.closed.is_set():
            return
        try:
            self._out.put_nowait(frame(OP_TEXT, text.encode("utf-8")))
        except queue.Full:  # a subscriber that does not read: dropped, as the controller drops it
            self.close()

    def _write(self) -> None:
        while True:
            data = self._out.get()
            if data is None or self.closed.is_set():
                return
            try:
                self.sock.sendall(data)
            except OSError:
                self.closed.set()
                return

    def serve(self) -> None:
        """Answer pings and closes until the client goes away."""
        try:
            while not self.closed.is_set():
                message = read_frame(self.stream)
                if message is None:
                    break
                opcode, payload = message
                if opcode == OP_CLOSE:
                    try:
                        self.sock.sendall(frame(OP_CLOSE, payload[:2]))
                    except OSError:
                        pass
                    break
                if opcode == OP_PING:
                    self._out.put(frame(OP_PONG, payload))
        except (OSError, ValueError, struct.error):
            pass
        finally:
            self.close()

    def close(self) -> None:
        if not self.closed.is_set():
            self.closed.set()
            try:
                self._out.put_nowait(None)
            except queue.Full:
                pass
            try:
                self.sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
