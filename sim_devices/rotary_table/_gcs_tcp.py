"""The GCS face on TCP: a PI controller's Ethernet interface (PI listens on port 50000).

The same ``GcsController`` logic as the serial face, one instance for this face (its own latched
error and its own ``FaultPlan``), served to any number of clients on loopback. As for Modbus TCP,
a ``TcpFaultProxy`` in front takes the transport faults (dropped reply, delay, garbage, truncation,
a flipped character, stall, disconnect); ``exception`` is taken by the controller.
"""

from __future__ import annotations

import select
import socket
import threading

from sim_devices._pty import line_framer
from sim_devices.faults import FaultPlan
from sim_devices.rotary_table._gcs import GcsController, corrupt_middle, split_commands
from sim_devices.rotary_table._physics import TablePhysics
from sim_devices.rotary_table._tcp_proxy import TcpFaultProxy

PI_TCP_PORT = 50000  # where a real PI controller listens; the twin takes an OS-chosen port by default

_POLL = 0.1  # s: how often the server loop looks at its stop flag


class GcsTcpServer:
    """Serve ``controller`` to TCP clients on ``127.0.0.1:port`` (0: OS-chosen) from one thread."""

    def __init__(self, controller: GcsController, port: int = 0) -> None:
        self.controller = controller
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind(("127.0.0.1", port))
        self._listener.listen(8)
        self.port = int(self._listener.getsockname()[1])
        self._buffers: dict[socket.socket, bytes] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="gcs tcp twin", daemon=True)

    def start(self) -> GcsTcpServer:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)
        for client in list(self._buffers):
            client.close()
        self._buffers.clear()
        self._listener.close()

    def _serve(self) -> None:
        while not self._stop.is_set():
            readable, _, _ = select.select([self._listener, *self._buffers], [], [], _POLL)
            for sock in readable:
                if sock is self._listener:
                    self._accept()
                else:
                    self._read(sock)

    def _accept(self) -> None:
        try:
            client, _ = self._listener.accept()
        except OSError:
            return
        client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        client.settimeout(1.0)  # an answer is a few bytes; a client that never reads is dropped
        self._buffers[client] = b""

    def _read(self, client: socket.socket) -> None:
        try:
            data = client.recv(4096)
        except OSError:
            data = b""
        if not data:
            self._drop(client)
            return
        commands, self._buffers[client] = split_commands(self._buffers[client] + data)
        for command in commands:
            answer = self.controller.handle(command)
            if answer:
                try:
                    client.sendall(answer)
                except OSError:
                    self._drop(client)
                    return

    def _drop(self, client: socket.socket) -> None:
        self._buffers.pop(client, None)
        client.close()


class GcsTcpTwin:
    """The GCS controller on TCP behind a fault proxy. ``start()`` → ``{"gcs_tcp_port", "gcs_tcp_direct_port"}``."""

    def __init__(self, physics: TablePhysics, *, port: int = 0) -> None:
        self.faults = FaultPlan()
        self.controller = GcsController(physics, self.faults)
        self._port = port
        self._server: GcsTcpServer | None = None
        self._proxy: TcpFaultProxy | None = None

    def start(self) -> dict[str, int]:
        try:
            self._server = GcsTcpServer(self.controller).start()
            self._proxy = TcpFaultProxy(("127.0.0.1", self._server.port), self.faults, framer=line_framer,
                                        corrupt=corrupt_middle, port=self._port, name="gcs tcp fault proxy").start()
        except BaseException:
            self.stop()
            raise
        return {"gcs_tcp_port": self._proxy.port, "gcs_tcp_direct_port": self._server.port}

    def stop(self) -> None:
        if self._proxy is not None:
            self._proxy.stop()
            self._proxy = None
        if self._server is not None:
            self._server.stop()
            self._server = None
