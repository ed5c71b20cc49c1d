"""A socketcand daemon (text protocol over TCP) serving the head's CAN channel.

Speaks what python-can's ``socketcand`` client expects, to the byte: ``< hi >`` on its own in
the first read, ``< ok >`` to ``< open <channel> >`` and ``< rawmode >``, then
``< frame <3 hex id> <sec>.<usec> <hex data> >`` per frame, with the receive timestamp the bus gave
the frame (as the real daemon forwards the kernel's). It pauses ``first_frame_pause``
seconds after the rawmode ``< ok >`` because the client reads that ``< ok >`` with one ``recv``
and fails if a frame arrives in the same read. In raw mode ``< send <id> <dlc> <b0> <b1> ... >``
puts a frame on the bus (the head's command input). Any number of clients.
"""

from __future__ import annotations

import select
import socket
import threading
import time
from collections.abc import Callable

CommandSink = Callable[[int, bytes], None]

_SEND_TIMEOUT = 0.5  # s: a client that stops reading for this long is dropped


class _Client:
    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.inbox = b""
        self.state = "greeted"  # -> "bus" -> "raw"
        self.raw_from = float("inf")  # monotonic time after which frames flow
        self.lock = threading.Lock()
        self.closed = False

    def send(self, data: bytes) -> bool:
        with self.lock:
            if self.closed:
                return False
            try:
                self.sock.sendall(data)
                return True
            except OSError:
                self.closed = True
                return False


class SocketcandServer:
    def __init__(self, host: str, port: int, channel: str, on_command: CommandSink,
                 first_frame_pause: float = 0.05) -> None:
        self.host, self.port, self.channel = host, int(port), channel
        self.on_command = on_command
        self.first_frame_pause = float(first_frame_pause)
        self._listener: socket.socket | None = None
        self._clients: list[_Client] = []
        self._clients_lock = threading.Lock()
        self._refuse_until = 0.0
        self._hold_until = 0.0
        self._held: list[bytes] = []  # frames kept back by hold(), sent when it ends
        self._outbox: list[bytes] = []  # frames since the last flush() (the clock thread's only)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.connections = 0

    # ------------------------------------------------------------------------------ lifecycle
    def start(self) -> dict:
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind((self.host, self.port))
        listener.listen(8)
        self._listener = listener
        self.port = listener.getsockname()[1]
        self._thread = threading.Thread(target=self._serve, args=(listener,), name="socketcand twin", daemon=True)
        self._thread.start()
        return {"host": self.host, "port": self.port, "channel": self.channel}

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        with self._clients_lock:
            clients, self._clients = self._clients, []
        for client in clients:
            self._close(client)
        if self._listener is not None:
            self._listener.close()
            self._listener = None

    # ------------------------------------------------------------------------------ the bus side
    def send_frame(self, can_id: int, data: bytes, timestamp: float) -> None:
        """Queue one frame for the next ``flush()`` (with no client and no hold, it is dropped at once,
        as the daemon drops frames nobody listens to)."""
        holding = time.monotonic() < self._hold_until
        if not (self._clients or holding):
            return
        seconds = int(timestamp)
        micros = int(round((timestamp - seconds) * 1e6))
        if micros >= 1_000_000:
            seconds, micros = seconds + 1, micros - 1_000_000
        line = f"< frame {can_id:03X} {seconds}.{micros:06d} {data.hex().upper()} >".encode("ascii")
        (self._held if holding else self._outbox).append(line)

    def flush(self) -> None:
        """Send the frames queued since the last flush, in one write per client (the held ones first,
        once the hold is over)."""
        if time.monotonic() < self._hold_until:
            return
        lines, self._held, self._outbox = self._held + self._outbox, [], []
        if lines:
            self._broadcast(b"".join(lines))

    def hold(self, seconds: float) -> None:
        """Hold every frame for ``seconds``, then send them in one burst (a congested link or a busy
        daemon host: the frames keep the timestamps they were received with)."""
        self._hold_until = max(self._hold_until, time.monotonic() + max(0.0, seconds))

    def send_garbage(self, junk: bytes) -> None:
        self.flush()
        self._broadcast(junk)

    def disconnect(self, seconds: float) -> None:
        """Close every client connection; refuse new ones for ``seconds``."""
        self._refuse_until = time.monotonic() + max(0.0, seconds)
        with self._clients_lock:
            clients, self._clients = self._clients, []
        for client in clients:
            self._close(client)

    def _broadcast(self, payload: bytes) -> None:
        now = time.monotonic()
        with self._clients_lock:
            ready = [c for c in self._clients if c.state == "raw" and now >= c.raw_from]
        for client in ready:
            if not client.send(payload):
                self._drop(client)

    # ------------------------------------------------------------------------------ server thread
    def _serve(self, listener: socket.socket) -> None:
        while not self._stop.is_set():
            with self._clients_lock:
                clients = list(self._clients)
            sockets = [listener] + [c.sock for c in clients]
            try:
                readable, _, _ = select.select(sockets, [], [], 0.05)
            except (OSError, ValueError):
                continue  # a client was closed under us by disconnect(); rebuild the list
            for sock in readable:
                if sock is listener:
                    self._accept(listener)
                    continue
                client = next((c for c in clients if c.sock is sock), None)
                if client is not None:
                    self._read(client)

    def _accept(self, listener: socket.socket) -> None:
        try:
            sock, _ = listener.accept()
        except OSError:
            return
        if time.monotonic() < self._refuse_until:
            sock.close()
            return
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(_SEND_TIMEOUT)
        client = _Client(sock)
        self.connections += 1
        if client.send(b"< hi >"):
            with self._clients_lock:
                self._clients.append(client)
        else:
            self._close(client)

    def _read(self, client: _Client) -> None:
        try:
            data = client.sock.recv(4096)
        except (TimeoutError, OSError):
            data = b""
        if not data:
            self._drop(client)
            return
        client.inbox += data
        while True:
            start, end = client.inbox.find(b"<"), client.inbox.find(b">")
            if start < 0 or end < 0:
                if start < 0:
                    client.inbox = b""
                break
            if end < start:  # a stray ">" before the next command
                client.inbox = client.inbox[start:]
                continue
            command = client.inbox[start + 1 : end].decode("ascii", "replace").split()
            client.inbox = client.inbox[end + 1 :]
            self._handle(client, command)

    def _handle(self, client: _Client, words: list[str]) -> None:
        if not words:
            client.send(b"< error empty command >")
        elif words[0] == "open" and client.state == "greeted":
            if len(words) == 2 and words[1] == self.channel:
                client.state = "bus"
                client.send(b"< ok >")
            else:
                client.send(b"< error could not open bus >")
        elif words[0] == "rawmode" and client.state in ("bus", "raw"):
            client.raw_from = time.monotonic() + self.first_frame_pause
            client.state = "raw"
            client.send(b"< ok >")
        elif words[0] == "send" and client.state == "raw":
            client.raw_from = min(client.raw_from, time.monotonic())  # it is past its handshake read
            self._handle_send(client, words[1:])
        elif words[0] == "echo":
            client.send(b"< echo >")
        else:
            client.send(b"< error unknown command >")

    def _handle_send(self, client: _Client, words: list[str]) -> None:
        try:
            can_id, dlc = int(words[0], 16), int(words[1], 16)
            data = bytes(int(word, 16) for word in words[2:])
        except (IndexError, ValueError):
            client.send(b"< error malformed send >")
            return
        if len(data) != dlc or dlc > 8 or can_id > 0x1FFFFFFF:
            client.send(b"< error malformed send >")
            return
        self.on_command(can_id, data)

    def _drop(self, client: _Client) -> None:
        with self._clients_lock:
            if client in self._clients:
                self._clients.remove(client)
        self._close(client)

    @staticmethod
    def _close(client: _Client) -> None:
        with client.lock:
            client.closed = True
            try:
                client.sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            client.sock.close()

