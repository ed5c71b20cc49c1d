"""The byte links a GCS controller is reached over: a serial line (pyserial) or TCP (a socket).

``GcsTable`` speaks the GCS line protocol over either; a link only moves bytes, with a deadline on
every read. Errors are ``OSError`` (``ConnectionError`` when the peer has gone), which the table
turns into typed device errors. Only a TCP link can be re-opened after it was lost.
"""

from __future__ import annotations

import socket
import time
from typing import Protocol

import serial


class GcsLink(Protocol):
    """Bytes to and from a GCS controller."""

    description: str
    reconnectable: bool

    @property
    def is_open(self) -> bool: ...

    def open(self) -> None:
        """Open the link (bounded); ``OSError`` or ``ValueError`` if it cannot be."""
        ...

    def close(self) -> None: ...

    def discard_input(self) -> None:
        """Throw away whatever has arrived and not been read (a late answer to an earlier request)."""
        ...

    def write(self, data: bytes) -> None: ...

    def read_line(self, deadline: float) -> bytes:
        """Bytes up to and including the next LF, or what arrived before ``deadline`` (monotonic)."""
        ...


class SerialLink:
    """A serial port (or any pyserial URL) at ``baudrate``."""

    reconnectable = False

    def __init__(self, port: str, baudrate: int, timeout: float) -> None:
        self.port, self.baudrate, self.timeout = port, baudrate, timeout
        self.description = port
        self._serial: serial.Serial | None = None

    @property
    def is_open(self) -> bool:
        return self._serial is not None

    def open(self) -> None:
        try:
            self._serial = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=self.timeout,
                                                 write_timeout=self.timeout)
        except serial.SerialException as exc:
            raise OSError(str(exc)) from None

    def close(self) -> None:
        port, self._serial = self._serial, None
        if port is not None:
            port.close()

    def _port(self) -> serial.Serial:
        if self._serial is None:
            raise ConnectionError("not open")
        return self._serial

    def discard_input(self) -> None:
        try:
            self._port().reset_input_buffer()
        except serial.SerialException as exc:
            raise OSError(str(exc)) from None

    def write(self, data: bytes) -> None:
        port = self._port()
        try:
            port.write(data)
            port.flush()
        except serial.SerialException as exc:
            raise OSError(str(exc)) from None

    def read_line(self, deadline: float) -> bytes:
        port = self._port()
        port.timeout = max(0.0, deadline - time.monotonic())
        try:
            return bytes(port.read_until(b"\n"))
        except serial.SerialException as exc:
            raise OSError(str(exc)) from None


class TcpLink:
    """A TCP connection to ``host:port`` (a PI controller's Ethernet interface)."""

    reconnectable = True

    def __init__(self, host: str, port: int, timeout: float) -> None:
        self.host, self.port, self.timeout = host, port, timeout
        self.description = f"tcp {host}:{port}"
        self._socket: socket.socket | None = None
        self._pending = b""

    @property
    def is_open(self) -> bool:
        return self._socket is not None

    def open(self) -> None:
        self.close()
        sock = socket.create_connection((self.host, self.port), timeout=self.timeout)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._socket = sock

    def close(self) -> None:
        sock, self._socket = self._socket, None
        self._pending = b""
        if sock is not None:
            sock.close()

    def _sock(self) -> socket.socket:
        if self._socket is None:
            raise ConnectionError("not connected")
        return self._socket

    def _lost(self, why: str) -> ConnectionError:
        self.close()
        return ConnectionError(why)

    def discard_input(self) -> None:
        sock = self._sock()
        self._pending = b""
        sock.settimeout(0.0)  # non-blocking: take only what is there
        while True:
            try:
                data = sock.recv(4096)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                raise self._lost(f"connection lost: {exc}") from None
            if not data:
                raise self._lost("the controller closed the connection")

    def write(self, data: bytes) -> None:
        sock = self._sock()
        sock.settimeout(self.timeout)
        try:
            sock.sendall(data)
        except OSError as exc:
            raise self._lost(f"send failed: {exc}") from None

    def read_line(self, deadline: float) -> bytes:
        sock = self._sock()
        while (index := self._pending.find(b"\n")) < 0:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                line, self._pending = self._pending, b""
                return line
            sock.settimeout(remaining)
            try:
                data = sock.recv(4096)
            except TimeoutError:
                continue
            except OSError as exc:
                raise self._lost(f"connection lost: {exc}") from None
            if not data:
                raise self._lost("the controller closed the connection")
            self._pending += data
        line, self._pending = self._pending[:index + 1], self._pending[index + 1:]
        return line
