"""A loopback TCP proxy that puts a ``FaultyRelay`` in front of a TCP server (Modbus TCP twin)."""

from __future__ import annotations

import select
import socket
import threading

from sim_devices._pty import FaultyRelay, ReplyFramer, chunk_framer
from sim_devices.faults import FaultPlan


class TcpFaultProxy:
    """Accept clients on ``127.0.0.1:port`` (0: OS-chosen) and relay each one to ``upstream``.

    ``disconnect`` closes the client's connection (the driver must reconnect); the other transport
    faults act on single replies as in ``FaultyRelay``.
    """

    def __init__(self, upstream: tuple[str, int], faults: FaultPlan, *, framer: ReplyFramer = chunk_framer,
                 corrupt=None, port: int = 0, name: str = "tcp proxy") -> None:
        self.upstream = upstream
        self.faults = faults
        self.framer = framer
        self.corrupt = corrupt
        self.name = name
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind(("127.0.0.1", port))
        self._listener.listen(8)
        self.port = self._listener.getsockname()[1]
        self._relays: list[tuple[FaultyRelay, socket.socket, socket.socket]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._accept_loop, name=name, daemon=True)

    def start(self) -> TcpFaultProxy:
        self._thread.start()
        return self

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            readable, _, _ = select.select([self._listener], [], [], 0.1)
            if not readable or self._stop.is_set():
                continue
            try:
                client, _ = self._listener.accept()
            except OSError:
                break
            try:
                upstream = socket.create_connection(self.upstream, timeout=2.0)
            except OSError:
                client.close()
                continue
            for sock in (client, upstream):
                sock.setblocking(False)
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            kwargs = {"corrupt": self.corrupt} if self.corrupt else {}
            relay = FaultyRelay(upstream.fileno(), client.fileno(), self.faults, framer=self.framer,
                                hang_up_on_disconnect=True, name=f"{self.name} relay", **kwargs)
            relay.on_close = lambda c=client, u=upstream: self._close_pair(c, u)
            with self._lock:
                finished = [r for r in self._relays if r[0].closed.is_set()]
                self._relays = [r for r in self._relays if not r[0].closed.is_set()]
                self._relays.append((relay, client, upstream))
            for old_relay, old_client, old_upstream in finished:  # connections ended by a disconnect
                old_relay.stop()
                old_client.close()
                old_upstream.close()
            relay.start()

    @staticmethod
    def _close_pair(client: socket.socket, upstream: socket.socket) -> None:
        for sock in (client, upstream):
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)
        self._listener.close()
        with self._lock:
            relays, self._relays = self._relays, []
        for relay, client, upstream in relays:
            relay.stop()
            client.close()
            upstream.close()
