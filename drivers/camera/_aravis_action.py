"""GigE Vision action commands: one trigger datagram that several cameras act on together.

Aravis 0.8 configures a camera's action (``ActionDeviceKey``, ``ActionSelector``, ``ActionGroupKey``,
``ActionGroupMask``, ``TriggerSource = Action1``) through its features but cannot send the command
itself, so the adapter sends it here: a GVCP ACTION_CMD (0x0100) — header 0x42, flags (bit 0:
acknowledge wanted), command, payload length, request id — with the device key, group key and
group mask (u32 each, big-endian). A camera acts if the keys equal its own and the masks share a bit.

``ActionGroup`` collects the cameras that share one (device key, group key, mask): each camera's
``trigger()`` marks it ready, and when every open member is ready ONE round of commands goes out —
to a broadcast address if the group has one (a real subnet: one datagram for all), else to each
camera's address in a row (loopback has no broadcast; the datagrams leave within microseconds).
So a ``CameraTriplet`` that triggers its three cameras fires them with one action.
"""

from __future__ import annotations

import socket
import struct
import threading

from drivers._errors import DeviceConnectionError

GVCP_PORT = 3956
ACTION_CMD = 0x0100


def action_command(device_key: int, group_key: int, group_mask: int, request_id: int, ack: bool = False) -> bytes:
    """The ACTION_CMD datagram."""
    payload = struct.pack(">III", device_key, group_key, group_mask)
    return struct.pack(">BBHHH", 0x42, 0x01 if ack else 0x00, ACTION_CMD, len(payload), request_id) + payload


class ActionGroup:
    """The cameras of one action (see the module docstring). Use ``ActionGroup.of(key)``."""

    _groups: dict[tuple[int, int, int, str | None], ActionGroup] = {}
    _registry_lock = threading.Lock()

    def __init__(self, device_key: int, group_key: int, group_mask: int, broadcast: str | None) -> None:
        self.device_key, self.group_key, self.group_mask = device_key, group_key, group_mask
        self.broadcast = broadcast
        self._members: dict[str, bool] = {}  # camera address → ready for the next round
        self._lock = threading.Lock()
        self._socket: socket.socket | None = None
        self._request_id = 0
        self.rounds = 0

    @classmethod
    def of(cls, device_key: int, group_key: int, group_mask: int, broadcast: str | None = None) -> ActionGroup:
        key = (device_key, group_key, group_mask, broadcast)
        with cls._registry_lock:
            group = cls._groups.get(key)
            if group is None:
                group = cls._groups[key] = cls(device_key, group_key, group_mask, broadcast)
            return group

    def join(self, address: str) -> None:
        with self._lock:
            self._members[address] = False
            if self._socket is None:
                self._socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                if self.broadcast is not None:
                    self._socket.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)

    def leave(self, address: str) -> None:
        with self._lock:
            self._members.pop(address, None)
            if not self._members and self._socket is not None:
                self._socket.close()
                self._socket = None

    def ready(self, address: str, device: str) -> bool:
        """Camera ``address`` is ready for a trigger; fires the round when it is the last. Returns
        whether this call fired it."""
        with self._lock:
            if address not in self._members:
                raise DeviceConnectionError(device, "fire action", "the camera is not in its action group (not open)")
            self._members[address] = True
            if not all(self._members.values()):
                return False
            targets = [self.broadcast] if self.broadcast is not None else list(self._members)
            self._request_id = self._request_id % 0xFFFF + 1
            datagram = action_command(self.device_key, self.group_key, self.group_mask, self._request_id)
            assert self._socket is not None
            try:
                for target in targets:
                    self._socket.sendto(datagram, (target, GVCP_PORT))
            except OSError as error:
                raise DeviceConnectionError(device, "fire action", f"could not send the command ({error})") from None
            for member in self._members:
                self._members[member] = False
            self.rounds += 1
            return True
