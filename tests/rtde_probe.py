"""A minimal RTDE output client for tests and benchmarks: every data package, decoded, with its arrival time.

The real ``ur_rtde`` receive client keeps only the latest state (its getters read one field at a
time), so checking that each package comes from one controller state, and that none is missing,
needs the packages themselves. This probe speaks the RTDE v2 handshake from the UR RTDE guide
(protocol version, output setup, start), then reads packages on a thread until ``close()``. It is
test code, written from the protocol description, not the twin's.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from dataclasses import dataclass
from typing import Any

FORMATS = {"DOUBLE": ("d", 1), "VECTOR6D": ("6d", 6), "VECTOR3D": ("3d", 3), "INT32": ("i", 1), "UINT32": ("I", 1),
           "UINT64": ("Q", 1), "UINT8": ("B", 1), "BOOL": ("?", 1), "VECTOR6INT32": ("6i", 6),
           "VECTOR6UINT32": ("6I", 6)}


@dataclass(frozen=True)
class Package:
    arrived: float  # time.monotonic() when read
    values: dict[str, Any]


class RTDEProbe:
    """Subscribe to ``names`` at ``frequency`` Hz on ``host``:30004 and collect every package."""

    def __init__(self, host: str, names: list[str], frequency: float = 500.0, timeout: float = 5.0) -> None:
        self.names = list(names)
        self.packages: list[Package] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._sock = socket.create_connection((host, 30004), timeout=timeout)
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._buffer = b""
        self._send(86, struct.pack(">H", 2))  # request protocol version 2
        kind, payload = self._read()
        if kind != 86 or payload[:1] != b"\x01":
            raise RuntimeError(f"RTDE probe: protocol version 2 refused ({kind}, {payload!r})")
        self._send(79, struct.pack(">d", frequency) + ",".join(self.names).encode())
        kind, payload = self._read()
        types = payload[1:].decode().split(",")
        if kind != 79 or "NOT_FOUND" in types:
            raise RuntimeError(f"RTDE probe: output setup refused: {types}")
        self._struct = struct.Struct(">B" + "".join(FORMATS[t][0] for t in types))
        self._sizes = [FORMATS[t][1] for t in types]
        self._send(83, b"")
        kind, payload = self._read()
        if kind != 83 or payload[:1] != b"\x01":
            raise RuntimeError("RTDE probe: start refused")
        self._sock.settimeout(0.5)
        self._thread = threading.Thread(target=self._collect, name="rtde-probe", daemon=True)
        self._thread.start()

    def _send(self, kind: int, payload: bytes) -> None:
        self._sock.sendall(struct.pack(">HB", len(payload) + 3, kind) + payload)

    def _read(self) -> tuple[int, bytes]:
        while True:
            if len(self._buffer) >= 3:
                size, kind = struct.unpack_from(">HB", self._buffer)
                if len(self._buffer) >= size:
                    payload, self._buffer = self._buffer[3:size], self._buffer[size:]
                    return kind, payload
            chunk = self._sock.recv(65536)
            if not chunk:
                raise ConnectionError("RTDE probe: the controller closed the connection")
            self._buffer += chunk

    def _collect(self) -> None:
        while not self._stop.is_set():
            try:
                kind, payload = self._read()
            except TimeoutError:
                continue
            except OSError:
                return
            if kind != 85:
                continue
            now = time.monotonic()
            flat = self._struct.unpack(payload)[1:]
            values: dict[str, Any] = {}
            offset = 0
            for name, size in zip(self.names, self._sizes):
                values[name] = flat[offset] if size == 1 else list(flat[offset:offset + size])
                offset += size
            with self._lock:
                self.packages.append(Package(now, values))

    def take(self) -> list[Package]:
        """Every package collected so far (and forget them)."""
        with self._lock:
            packages, self.packages = self.packages, []
        return packages

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        try:
            self._send(80, b"")  # pause, as a polite client does
        except OSError:
            pass
        self._sock.close()

    def __enter__(self) -> RTDEProbe:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
