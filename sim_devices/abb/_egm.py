"""EGM position streaming: ``EgmRobot`` messages over UDP, from the twin's own protobuf encoder.

A minimal protocol-buffers writer (varints, 64-bit doubles, length-delimited sub-messages, proto2's
unpacked repeated fields) and the field numbers of ABB's ``egm.proto`` (RobotWare 6, EGM 1.x)::

    EgmRobot       header 1, feedBack 2, planned 3, motorState 4, mciState 5, mciConvergenceMet 6,
                   rapidExecState 8, utilizationRate 10
    EgmHeader      seqno 1 (uint32), tm 2 (uint32, ms), mtype 3 (enum; MSGTYPE_DATA = 2)
    EgmFeedBack /  joints 1 (EgmJoints: repeated double 1, degrees), cartesian 2 (EgmPose:
    EgmPlanned     pos 1 (x, y, z = 1, 2, 3, mm), orient 2 (u0..u3 = 1..4)), time 4 (EgmClock: sec 1,
                   usec 2, uint64)
    EgmMotorState  state 1 (MOTORS_ON = 1, MOTORS_OFF = 2)
    EgmMCIState    state 1 (MCI_STOPPED = 2: streaming without guided motion)
    EgmRapidCtrlExecState  state 1 (RAPID_STOPPED = 1, RAPID_RUNNING = 2)

``EgmStream`` is a controller-cycle listener: every ``sample_rate`` it sends one message to the
"UCdevice" remote address, from a socket bound to the twin's loopback address. The cartesian pose
is tool0's in the base frame (``EGMStreamStart`` without ``\\Tool``/``\\WObj``). Faults: a stall
(no packets for ``seconds``) and lost packets (``count`` packets not sent, their sequence numbers
skipped, as a lossy network shows them to the sensor).
"""

from __future__ import annotations

import socket
import struct
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from sim_devices._transforms import invert, pose6_to_matrix
from sim_devices.abb._kinematics import matrix_to_quaternion
from sim_devices.arm import CycleState
from sim_devices.faults import FaultKind, FaultPlan

MSGTYPE_DATA = 2
MOTORS_ON, MOTORS_OFF = 1, 2
MCI_STOPPED = 2
RAPID_STOPPED, RAPID_RUNNING = 1, 2


def _varint(value: int) -> bytes:
    out = bytearray()
    value &= (1 << 64) - 1
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def varint_field(number: int, value: int) -> bytes:
    return _varint(number << 3) + _varint(int(value))


def double_field(number: int, value: float) -> bytes:
    return _varint(number << 3 | 1) + struct.pack("<d", float(value))


def message_field(number: int, body: bytes) -> bytes:
    return _varint(number << 3 | 2) + _varint(len(body)) + body


def joints_message(values_deg) -> bytes:
    return b"".join(double_field(1, v) for v in values_deg)


def pose_message(position_mm, quaternion) -> bytes:
    pos = b"".join(double_field(i + 1, v) for i, v in enumerate(position_mm))
    orient = b"".join(double_field(i + 1, v) for i, v in enumerate(quaternion))
    return message_field(1, pos) + message_field(2, orient)


def clock_message(seconds: float) -> bytes:
    sec = int(seconds)
    return varint_field(1, sec) + varint_field(2, int(round((seconds - sec) * 1e6)))


def encode_robot(seqno: int, tm_ms: int, joints_deg, flange_mm, flange_quat, planned_joints_deg, planned_mm,
                 planned_quat, clock: float, motors_on: bool, rapid_running: bool) -> bytes:
    """One ``EgmRobot`` message (see the module docstring for the fields)."""
    header = varint_field(1, seqno & 0xFFFFFFFF) + varint_field(2, tm_ms & 0xFFFFFFFF) + varint_field(3, MSGTYPE_DATA)
    feedback = (message_field(1, joints_message(joints_deg)) + message_field(2, pose_message(flange_mm, flange_quat))
                + message_field(4, clock_message(clock)))
    planned = (message_field(1, joints_message(planned_joints_deg))
               + message_field(2, pose_message(planned_mm, planned_quat)) + message_field(4, clock_message(clock)))
    return (message_field(1, header) + message_field(2, feedback) + message_field(3, planned)
            + message_field(4, varint_field(1, MOTORS_ON if motors_on else MOTORS_OFF))
            + message_field(5, varint_field(1, MCI_STOPPED)) + varint_field(6, 0)
            + message_field(8, varint_field(1, RAPID_RUNNING if rapid_running else RAPID_STOPPED))
            + double_field(10, 0.0))


def decode_fields(data: bytes) -> dict[int, list[Any]]:
    """Field number → raw values of one message (varints as ints, doubles as floats, the rest bytes):
    enough to read the header of an ``EgmSensor`` the sensor sends back."""
    fields: dict[int, list[Any]] = {}
    i = 0
    while i < len(data):
        key, i = _read_varint(data, i)
        number, wire = key >> 3, key & 7
        value: Any
        if wire == 0:
            value, i = _read_varint(data, i)
        elif wire == 1:
            (value,) = struct.unpack_from("<d", data, i)
            i += 8
        elif wire == 2:
            length, i = _read_varint(data, i)
            value, i = data[i:i + length], i + length
        elif wire == 5:
            (value,) = struct.unpack_from("<f", data, i)
            i += 4
        else:
            raise ValueError(f"protobuf: wire type {wire} is not used by EGM")
        fields.setdefault(number, []).append(value)
    return fields


def _read_varint(data: bytes, i: int) -> tuple[int, int]:
    shift = value = 0
    while True:
        if i >= len(data):
            raise ValueError("protobuf: truncated varint")
        byte = data[i]
        i += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, i
        shift += 7


class EgmStream:
    """Sends ``EgmRobot`` to ``remote`` every ``every`` controller cycles while ``active``.

    Parameters
    ----------
    host : str
        The twin's loopback address (the source of the packets).
    remote : (str, int)
        The sensor's address ("UCdevice" remote address and port).
    every : int
        Controller cycles per packet.
    period : float
        Controller cycle (s): ``tm`` is the cycle's controller time in ms.
    tcp_offset, state : callables
        ``tcp_offset() -> [x, y, z, rx, ry, rz]`` (the TCP in tool0) and ``state() -> (motors_on,
        rapid_running)``.
    faults : FaultPlan, optional
        ``stall`` faults are taken from it: ``packets`` lost ones, or none sent for ``seconds`` (1 s).
    """

    def __init__(self, host: str, remote: tuple[str, int], every: int, period: float,
                 tcp_offset: Callable[[], Any], state: Callable[[], tuple[bool, bool]],
                 faults: FaultPlan | None = None) -> None:
        self.faults = faults
        self.remote = remote
        self.every = max(1, int(every))
        self.period = period
        self.tcp_offset = tcp_offset
        self.state = state
        self.active = False
        self.seqno = 0
        self.sent = 0
        self.lost = 0
        self.stall_until = -1.0  # controller time until which nothing is sent
        self.drop = 0  # packets still to lose
        self.received = 0  # EgmSensor packets from the sensor
        self._lock = threading.Lock()
        self.socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.socket.setblocking(False)
        self.socket.bind((host, 0))
        self._closed = False
        self._reader = threading.Thread(target=self._read, name="abb-egm-read", daemon=True)
        self._reader.start()

    def close(self) -> None:
        self._closed = True
        self.socket.close()

    def on_cycle(self, state: CycleState) -> None:
        """The controller cycle's listener: one packet every ``every`` cycles."""
        if not self.active or state.cycle % self.every:
            return
        stamp = state.cycle * self.period
        if self.faults is not None and self.faults.peek(FaultKind.STALL) is not None:
            armed = self.faults.take(FaultKind.STALL)
            if armed is not None:
                if "packets" in armed.params:
                    self.drop += int(armed.params["packets"])
                else:
                    self.stall_until = stamp + float(armed.params.get("seconds", 1.0))
        with self._lock:
            self.seqno += 1
            seqno = self.seqno
            if stamp < self.stall_until:
                self.lost += 1
                return
            if self.drop > 0:
                self.drop -= 1
                self.lost += 1
                return
        f = state.fields
        q_actual, q_target = np.asarray(f["actual_q"]), np.asarray(f["target_q"])
        # tool0 from the cycle's TCP poses and the TCP offset: two small products instead of two FKs.
        to_flange = invert(pose6_to_matrix(self.tcp_offset()))
        actual = pose6_to_matrix(f["actual_TCP_pose"]) @ to_flange
        target = pose6_to_matrix(f["target_TCP_pose"]) @ to_flange
        motors_on, running = self.state()
        message = encode_robot(seqno, int(round(stamp * 1000)), np.degrees(q_actual), actual[:3, 3] * 1e3,
                               matrix_to_quaternion(actual[:3, :3]), np.degrees(q_target), target[:3, 3] * 1e3,
                               matrix_to_quaternion(target[:3, :3]), stamp, motors_on, running)
        try:
            self.socket.sendto(message, self.remote)
            self.sent += 1
        except OSError:  # nobody listens (ICMP unreachable) or the buffer is full: a lost datagram
            with self._lock:
                self.lost += 1

    def _read(self) -> None:
        """Count what the sensor sends back (corrections are not modelled)."""
        import select

        while not self._closed:
            try:
                ready, _, _ = select.select([self.socket], [], [], 0.2)
                if ready:
                    data = self.socket.recv(65536)
                    decode_fields(data)
                    self.received += 1
            except (OSError, ValueError):
                if self._closed:
                    return

    def stats(self) -> dict[str, Any]:
        with self._lock:
            return {"active": self.active, "seqno": self.seqno, "sent": self.sent, "lost": self.lost,
                    "received": self.received, "remote": list(self.remote)}
