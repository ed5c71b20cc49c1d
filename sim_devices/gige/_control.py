"""The twin camera's control channel: a GVCP server on ``host``:3956.

It decodes each command (``_wire``), answers it from the camera's ``RegisterSpace``, and keeps the
control privilege: one host at a time holds it (CCP bit 1 written), writes from any other are refused
with ACCESS_DENIED, and the holder must send something within ``GevHeartbeatTimeout`` or the camera
drops it (``on_control_lost``: the camera stops acquiring). PACKETRESEND and ACTION go to the camera
(``on_resend``, ``on_action``); while ``unresponsive()`` nothing is read or answered.
"""

from __future__ import annotations

import select
import socket
import threading
import time
from collections.abc import Callable

from sim_devices.gige import _features as f
from sim_devices.gige import _wire as w
from sim_devices.gige._registers import RegisterError, RegisterSpace

POLL = 0.05  # s the server waits for a datagram before it looks at the heartbeat again

Sender = tuple[str, int]


class ControlChannel:
    """GVCP server (see the module docstring).

    Parameters
    ----------
    host : str
        Bound with UDP 3956.
    registers : RegisterSpace
    on_resend : callable(block_id, first, last)
    on_action : callable(flags, payload) → None
        An ACTION_CMD whose keys the camera checks itself.
    on_control_lost : callable()
        The holder's heartbeat expired, or it released control.
    unresponsive : callable() → bool
        The fault: while true the camera neither reads nor answers.
    """

    def __init__(self, host: str, registers: RegisterSpace, *, on_resend: Callable[[int, int, int], None],
                 on_action: Callable[[int, bytes], None], on_control_lost: Callable[[], None],
                 unresponsive: Callable[[], bool]) -> None:
        self.registers = registers
        self._on_resend, self._on_action = on_resend, on_action
        self._on_control_lost, self._unresponsive = on_control_lost, unresponsive
        self.socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.socket.bind((host, w.GVCP_PORT))
        except OSError as exc:
            self.socket.close()
            raise OSError(f"gige twin: cannot bind GVCP {host}:{w.GVCP_PORT} ({exc.strerror})") from None
        self.controller: Sender | None = None
        self.commands = 0
        self.control_lost = 0
        self._last_heard = 0.0
        self._lock = threading.RLock()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._handlers: dict[int, Callable[[w.Command, Sender], bytes | None]] = {
            w.DISCOVERY_CMD: self._discovery, w.READREG_CMD: self._read_registers,
            w.WRITEREG_CMD: self._write_registers, w.READMEM_CMD: self._read_memory,
            w.WRITEMEM_CMD: self._write_memory, w.PACKETRESEND_CMD: self._packet_resend, w.ACTION_CMD: self._action}

    def start(self, name: str) -> None:
        self._thread = threading.Thread(target=self._serve, name=f"gige-{name}-gvcp", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(10.0)
            self._thread = None
        self.socket.close()

    # ------------------------------------------------------------------ the loop
    def _serve(self) -> None:
        while not self._stopping.is_set():
            ready, _, _ = select.select([self.socket], [], [], POLL)
            self._check_heartbeat()
            if not ready:
                continue
            try:
                datagram, sender = self.socket.recvfrom(65536)
            except OSError:
                continue
            if self._unresponsive():
                continue  # a camera that has stopped answering reads nothing either
            try:
                command = w.decode_command(datagram)
            except w.MalformedPacket:
                continue
            reply = self._handle(command, sender)
            if reply is not None and command.wants_ack:
                try:
                    self.socket.sendto(reply, sender)
                except OSError:
                    pass

    def _check_heartbeat(self) -> None:
        with self._lock:
            if self.controller is None:
                return
            timeout = self.registers.get(f.HEARTBEAT_TIMEOUT) / 1000.0
            if time.monotonic() - self._last_heard > timeout or self._unresponsive():
                self._release()
                self.control_lost += 1

    def _release(self) -> None:
        self.controller = None
        self.registers.set(f.CONTROL_CHANNEL_PRIVILEGE, 0)
        self._on_control_lost()

    def _handle(self, command: w.Command, sender: Sender) -> bytes | None:
        self.commands += 1
        with self._lock:
            if self.controller == sender:
                self._last_heard = time.monotonic()
        handler = self._handlers.get(command.command)
        if handler is None:
            return w.encode_ack(command.command, command.request_id, status=w.STATUS_NOT_IMPLEMENTED)
        return handler(command, sender)

    # ------------------------------------------------------------------ commands
    def _discovery(self, command: w.Command, sender: Sender) -> bytes:
        return w.encode_ack(command.command, command.request_id, self.registers.discovery_data())

    def _read_registers(self, command: w.Command, sender: Sender) -> bytes:
        values = []
        for i in range(0, len(command.payload) - 3, 4):
            address = int.from_bytes(command.payload[i:i + 4], "big")
            try:
                values.append(self.registers.read(address, 4))
            except RegisterError as error:
                return w.encode_ack(command.command, command.request_id, b"".join(values), status=error.status)
        return w.encode_ack(command.command, command.request_id, b"".join(values))

    def _may_write(self, address: int, value: int, sender: Sender) -> int | None:
        """None if ``sender`` may write ``value`` at ``address``; else the status to refuse with."""
        with self._lock:
            if address == f.CONTROL_CHANNEL_PRIVILEGE:
                if self.controller not in (None, sender):
                    return w.STATUS_ACCESS_DENIED
                if value & (f.CCP_CONTROL | f.CCP_EXCLUSIVE):
                    self.controller = sender
                    self._last_heard = time.monotonic()
                elif self.controller == sender:
                    self._release()
                return None
            return None if self.controller == sender else w.STATUS_ACCESS_DENIED

    def _write_registers(self, command: w.Command, sender: Sender) -> bytes:
        written = 0
        status = w.STATUS_SUCCESS
        for i in range(0, len(command.payload) - 7, 8):
            address = int.from_bytes(command.payload[i:i + 4], "big")
            value = command.payload[i + 4:i + 8]
            refusal = self._may_write(address, int.from_bytes(value, "big"), sender)
            if refusal is not None:
                status = refusal
                break
            try:
                self.registers.write(address, value)
            except RegisterError as error:
                status = error.status
                break
            written += 1
        return w.encode_ack(command.command, command.request_id, written.to_bytes(4, "big"), status=status)

    def _read_memory(self, command: w.Command, sender: Sender) -> bytes:
        if len(command.payload) < 8:
            return w.encode_ack(command.command, command.request_id, status=w.STATUS_INVALID_PARAMETER)
        address = int.from_bytes(command.payload[0:4], "big")
        count = int.from_bytes(command.payload[6:8], "big")
        if count > w.READMEM_MAX:
            return w.encode_ack(command.command, command.request_id, status=w.STATUS_INVALID_PARAMETER)
        try:
            data = self.registers.read(address, count)
        except RegisterError as error:
            return w.encode_ack(command.command, command.request_id, status=error.status)
        return w.encode_ack(command.command, command.request_id, command.payload[0:4] + data)

    def _write_memory(self, command: w.Command, sender: Sender) -> bytes:
        address = int.from_bytes(command.payload[0:4], "big")
        data = command.payload[4:]
        for i in range(0, len(data) - 3, 4):
            refusal = self._may_write(address + i, int.from_bytes(data[i:i + 4], "big"), sender)
            if refusal is not None:
                return w.encode_ack(command.command, command.request_id, i.to_bytes(4, "big"), status=refusal)
        try:
            self.registers.write(address, data)
        except RegisterError as error:
            return w.encode_ack(command.command, command.request_id, bytes(4), status=error.status)
        return w.encode_ack(command.command, command.request_id, len(data).to_bytes(4, "big"))

    def _packet_resend(self, command: w.Command, sender: Sender) -> None:
        if len(command.payload) >= 12:
            block_id = int.from_bytes(command.payload[2:4], "big")
            first = int.from_bytes(command.payload[4:8], "big") & 0xFFFFFF
            last = int.from_bytes(command.payload[8:12], "big") & 0xFFFFFF
            self._on_resend(block_id, first, last)
        return None  # served on the stream channel; a resend is never acknowledged

    def _action(self, command: w.Command, sender: Sender) -> bytes:
        if len(command.payload) < 12:
            return w.encode_ack(command.command, command.request_id, status=w.STATUS_INVALID_PARAMETER)
        self._on_action(command.flags, command.payload)
        return w.encode_ack(command.command, command.request_id)
