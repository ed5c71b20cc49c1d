"""The twin camera's memory: bootstrap registers, device registers and the GenICam XML, one address space.

Reads and writes go through ``read``/``write`` (bytes, any 4-byte-aligned address the space holds);
``watch(address, callback)`` calls ``callback(value)`` after a 32-bit register at ``address`` (or an
8-byte float register starting there) was written, so the camera reacts to a command register or a
setting. Everything is big-endian, as GVCP carries it.
"""

from __future__ import annotations

import ipaddress
import struct
import threading
from collections.abc import Callable

from sim_devices.gige import _features as f

_U32 = struct.Struct(">I")
_F64 = struct.Struct(">d")


class RegisterError(ValueError):
    """An access the device refuses; ``status`` is the GVCP status to answer with."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


class RegisterSpace:
    """Bootstrap + device registers + XML of one camera (see the module docstring).

    Parameters
    ----------
    host : str
        The camera's IPv4 address (the current IP register and the discovery answer).
    vendor, model, serial, version : str
        The identity registers.
    mac : bytes
        Six bytes.
    """

    def __init__(self, host: str, vendor: str, model: str, serial: str, version: str, mac: bytes) -> None:
        self.xml = f.genicam_xml(vendor, model)
        self._memory = bytearray(f.XML_ADDRESS + len(self.xml))
        self._memory[f.XML_ADDRESS:f.XML_ADDRESS + len(self.xml)] = self.xml
        self._writable: set[int] = set()
        self._watchers: dict[int, Callable[[int], None]] = {}
        self._float_addresses = {feature.address for feature in f.FEATURES if feature.kind == "float"}
        self._lock = threading.RLock()
        self._put(f.VERSION, 0x00020000)  # GigE Vision 2.0
        self._put(f.DEVICE_MODE, 0x80000001)  # big-endian device, UTF-8
        self._put(f.MAC_HIGH, int.from_bytes(mac[:2], "big"))
        self._put(f.MAC_LOW, int.from_bytes(mac[2:], "big"))
        self._put(f.SUPPORTED_IP_CONFIGURATION, 0x7)
        self._put(f.CURRENT_IP_CONFIGURATION, 0x1)  # persistent IP
        self._put(f.CURRENT_IP, int(ipaddress.IPv4Address(host)))
        self._put(f.CURRENT_SUBNET_MASK, 0xFF000000)
        for address, text, size in ((f.MANUFACTURER_NAME, vendor, 32), (f.MODEL_NAME, model, 32),
                                    (f.DEVICE_VERSION, version, 32), (f.MANUFACTURER_INFO, "simulated twin", 48),
                                    (f.SERIAL_NUMBER, serial, 16), (f.USER_NAME, "", 16)):
            self._put_string(address, text, size)
        # The URL's address and length are hexadecimal; written with 0x so that no client can read a
        # bare "20000" as decimal (pyGigEVision 0.2.2 does).
        self._put_string(f.FIRST_URL, f"Local:opr_gige_twin.xml;0x{f.XML_ADDRESS:x};0x{len(self.xml):x}", 512)
        self._put(f.NETWORK_INTERFACES, 1)
        self._put(f.STREAM_CHANNELS, 1)
        self._put(f.GVCP_CAPABILITY, f.CAPABILITIES)
        self._put(f.HEARTBEAT_TIMEOUT, 3000)
        self._put(f.STREAM_PACKET_SIZE, 1500)
        writable = [f.USER_NAME + i for i in range(0, 16, 4)]
        writable += [f.HEARTBEAT_TIMEOUT, f.TIMESTAMP_CONTROL, f.CONTROL_CHANNEL_PRIVILEGE, f.STREAM_PORT,
                     f.STREAM_PACKET_SIZE, f.STREAM_PACKET_DELAY, f.STREAM_DESTINATION, f.ACTION_DEVICE_KEY]
        for feature in f.FEATURES:
            if feature.access != "RO":
                writable += [feature.address + i for i in range(0, feature.length, 4)]
        self._writable.update(writable)

    # ------------------------------------------------------------------ the camera's side
    def _put(self, address: int, value: int) -> None:
        _U32.pack_into(self._memory, address, value & 0xFFFFFFFF)

    def _put_string(self, address: int, text: str, size: int) -> None:
        data = text.encode()[: size - 1]
        self._memory[address:address + size] = data + bytes(size - len(data))

    def set(self, address: int, value: int) -> None:
        """Set a 32-bit register (the camera's own values: read-only ones too)."""
        with self._lock:
            self._put(address, value)

    def get(self, address: int) -> int:
        with self._lock:
            return int(_U32.unpack_from(self._memory, address)[0])

    def set_float(self, address: int, value: float) -> None:
        with self._lock:
            _F64.pack_into(self._memory, address, float(value))

    def get_float(self, address: int) -> float:
        with self._lock:
            return float(_F64.unpack_from(self._memory, address)[0])

    def set_u64(self, address: int, value: int) -> None:
        with self._lock:
            self._put(address, value >> 32)
            self._put(address + 4, value)

    def watch(self, address: int, callback: Callable[[int], None]) -> None:
        """Call ``callback(new value)`` after a client writes the register at ``address``; a
        ``RegisterError`` it raises refuses the write (the old value is put back)."""
        self._watchers[address] = callback

    # ------------------------------------------------------------------ the client's side (GVCP)
    def read(self, address: int, size: int) -> bytes:
        if address % 4 or size % 4 or size <= 0:
            raise RegisterError(0x8005, f"read of {size} bytes at 0x{address:x} is not 4-byte aligned")
        if address < 0 or address + size > len(self._memory):
            raise RegisterError(0x8003, f"no memory at 0x{address:x} (+{size})")
        with self._lock:
            return bytes(self._memory[address:address + size])

    def write(self, address: int, data: bytes) -> None:
        if address % 4 or len(data) % 4 or not data:
            raise RegisterError(0x8005, f"write of {len(data)} bytes at 0x{address:x} is not 4-byte aligned")
        words = range(address, address + len(data), 4)
        denied = [a for a in words if a not in self._writable]
        if denied:
            exists = all(0 <= a < len(self._memory) for a in denied)
            raise RegisterError(0x8004 if exists else 0x8003, f"register 0x{denied[0]:x} is not writable")
        with self._lock:
            before = bytes(self._memory[address:address + len(data)])
            self._memory[address:address + len(data)] = data
        try:
            for a in words:
                callback = self._watchers.get(a)
                if callback is None:
                    continue
                if a in self._float_addresses and a + 8 > address + len(data):
                    continue  # half of a float: wait for the whole value
                callback(self.get(a))
        except RegisterError:
            with self._lock:  # the camera refused the value: the register keeps its old one
                self._memory[address:address + len(data)] = before
            raise

    def discovery_data(self) -> bytes:
        """What a DISCOVERY_ACK carries: the first bytes of the bootstrap registers."""
        return self.read(0, f.DISCOVERY_DATA_SIZE)
