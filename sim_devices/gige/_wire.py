"""GVCP and GVSP on the wire: the twin's own encoding, written from the GigE Vision protocol.

Never shared with the driver (``drivers.camera`` speaks through Aravis): a convention error here
fails the tests against Aravis and pyGigEVision instead of cancelling out.

GVCP (control, UDP 3956), every field big-endian
-------------------------------------------------
- command: ``0x42``, flags (bit 0: acknowledge required; 0x10 on DISCOVERY: broadcast ack
  allowed; 0x80 on ACTION: the command carries an action time), command (u16), payload length
  (u16), request id (u16); then the payload.
- acknowledge: status (u16, 0 = success; 0x8xxx an error code), acknowledge code (command + 1,
  u16), payload length (u16), the request's id (u16); then the payload.

Commands the twin answers: DISCOVERY (ack: the first 0xF8 bytes of the bootstrap registers),
READREG (n addresses → n values), WRITEREG (n address/value pairs → the index of the last one
written), READMEM (address, reserved u16, count u16 → the address echoed and the bytes),
WRITEMEM (address, data → the index of the bytes written), PACKETRESEND (block id, first and last
packet id: no ack, the packets come again on the stream channel), ACTION (device key, group key,
group mask, optional 64-bit action time).

GVSP (stream, UDP to the host's port) with 16-bit block ids
------------------------------------------------------------
Header: status (u16), block id (u16, 1…65535, never 0), packet format (u8: 1 leader, 2 trailer,
3 payload; bit 7 clear: standard ids), packet id (u24: 0 for the leader, 1…n payload, n + 1
trailer). Leader (image): reserved u16, payload type u16 (1 = image), timestamp (u64, camera
ticks), pixel format (PFNC, u32), width, height, offset x, offset y (u32), padding x, padding y
(u16). Payload: the image bytes, ``packet_size − 36`` per packet (IP 20 + UDP 8 + GVSP 8 bytes of
the datagram the packet size counts). Trailer: reserved u16, payload type u16, size y (u32).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

GVCP_PORT = 3956
COMMAND_KEY = 0x42
FLAG_ACK_REQUIRED = 0x01
FLAG_ACTION_TIME = 0x80

DISCOVERY_CMD = 0x0002
PACKETRESEND_CMD = 0x0040
READREG_CMD = 0x0080
WRITEREG_CMD = 0x0082
READMEM_CMD = 0x0084
WRITEMEM_CMD = 0x0086
PENDING_ACK = 0x0089
ACTION_CMD = 0x0100

STATUS_SUCCESS = 0x0000
STATUS_NOT_IMPLEMENTED = 0x8001
STATUS_INVALID_PARAMETER = 0x8002
STATUS_INVALID_ADDRESS = 0x8003
STATUS_WRITE_PROTECT = 0x8004
STATUS_BAD_ALIGNMENT = 0x8005
STATUS_ACCESS_DENIED = 0x8006
STATUS_PACKET_UNAVAILABLE = 0x800C
STATUS_BUSY = 0x8007

READMEM_MAX = 536  # bytes a READMEM may ask for (a 576-byte GVCP datagram)

GVSP_LEADER = 0x01
GVSP_TRAILER = 0x02
GVSP_PAYLOAD = 0x03
PAYLOAD_TYPE_IMAGE = 0x0001
GVSP_DATAGRAM_OVERHEAD = 20 + 8 + 8  # IP + UDP + GVSP header: what a packet size counts beyond the data

_COMMAND = struct.Struct(">BBHHH")
_ACK = struct.Struct(">HHHH")
_GVSP = struct.Struct(">HHI")
_LEADER = struct.Struct(">HHQIIIIIHH")
_TRAILER = struct.Struct(">HHI")


class MalformedPacket(ValueError):
    """A datagram that is not a GVCP command."""


@dataclass(frozen=True)
class Command:
    """One decoded GVCP command."""

    flags: int
    command: int
    request_id: int
    payload: bytes

    @property
    def wants_ack(self) -> bool:
        return bool(self.flags & FLAG_ACK_REQUIRED)


def decode_command(datagram: bytes) -> Command:
    """The command in ``datagram``; ``MalformedPacket`` if it is none (wrong key, short, bad length)."""
    if len(datagram) < _COMMAND.size:
        raise MalformedPacket(f"{len(datagram)} bytes: shorter than a GVCP header")
    key, flags, command, length, request_id = _COMMAND.unpack_from(datagram)
    if key != COMMAND_KEY:
        raise MalformedPacket(f"key 0x{key:02x} is not a GVCP command")
    payload = datagram[_COMMAND.size:_COMMAND.size + length]
    if len(payload) != length:
        raise MalformedPacket(f"payload of {len(payload)} bytes, header says {length}")
    return Command(flags, command, request_id, payload)


def encode_command(command: int, request_id: int, payload: bytes = b"", flags: int = FLAG_ACK_REQUIRED) -> bytes:
    """A GVCP command datagram (the twin's tests and tools use it)."""
    return _COMMAND.pack(COMMAND_KEY, flags, command, len(payload), request_id) + payload


def encode_ack(command: int, request_id: int, payload: bytes = b"", status: int = STATUS_SUCCESS) -> bytes:
    """The acknowledge of ``command`` (its code + 1) for ``request_id``."""
    return _ACK.pack(status, command + 1, len(payload), request_id) + payload


def encode_pending_ack(request_id: int, milliseconds: int) -> bytes:
    """PENDING_ACK: the answer will take up to ``milliseconds`` more."""
    return _ACK.pack(STATUS_SUCCESS, PENDING_ACK, 4, request_id) + struct.pack(">HH", 0, milliseconds)


def gvsp_header(block_id: int, packet_format: int, packet_id: int, status: int = STATUS_SUCCESS) -> bytes:
    return _GVSP.pack(status, block_id, (packet_format << 24) | (packet_id & 0xFFFFFF))


def gvsp_leader(block_id: int, timestamp: int, pixel_format: int, width: int, height: int,
                offset_x: int, offset_y: int) -> bytes:
    """The leader packet of an image block (packet id 0)."""
    return gvsp_header(block_id, GVSP_LEADER, 0) + _LEADER.pack(
        0, PAYLOAD_TYPE_IMAGE, timestamp & 0xFFFFFFFFFFFFFFFF, pixel_format, width, height, offset_x, offset_y, 0, 0)


def gvsp_trailer(block_id: int, packet_id: int, height: int) -> bytes:
    return gvsp_header(block_id, GVSP_TRAILER, packet_id) + _TRAILER.pack(0, PAYLOAD_TYPE_IMAGE, height)


def gvsp_payload(block_id: int, packet_id: int, data: bytes | memoryview) -> bytes:
    return gvsp_header(block_id, GVSP_PAYLOAD, packet_id) + bytes(data)


def gvsp_unavailable(block_id: int, packet_id: int) -> bytes:
    """Answer to a resend of a packet the camera no longer holds."""
    return gvsp_header(block_id, GVSP_PAYLOAD, packet_id, STATUS_PACKET_UNAVAILABLE)


def next_block_id(block_id: int) -> int:
    """Block ids run 1…65535 and wrap to 1 (0 is not a valid id)."""
    return 1 if block_id >= 0xFFFF else block_id + 1
