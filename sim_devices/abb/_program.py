"""The binary motion program and its joint log, as the RAPID module ``motion_program_exec`` reads
and ``motion_program_logger`` writes them (file format version 10011).

Written from the RAPID side (``robot/HOME/motion_program_exec.mod`` of abb_motion_program_exec,
whose ``try_motion_program_read_*`` functions define the layout), not from the Python client that
writes it: every number is a little-endian IEEE float (``UnpackRawBytes ... \\Float4``); a string
is its length as a number followed by 32 bytes of ASCII; a record is its fields in declaration
order. The file is::

    version · tooldata · wobjdata · loaddata (gripload) · string timestamp · seqno · egm config
    then commands: cmd_num · opcode · parameters, until the file ends

A file that ends inside the header is a RAPID error (``ERR_FILESIZE`` / ``ERR_INVALID_MP_FILE``);
a file that ends inside a command simply ends the program (the module's ``try_..._run_next_cmd``
returns FALSE), and the twin reproduces both.

The joint log (``log-<timestamp>.bin`` on the RAMDISK) is the version, the timestamp and the
column header as length-prefixed ASCII (no padding: ``PackRawBytes \\ASCII``), then one row of
float32 ``timestamp, cmdnum, J1 … J6`` (s, -, degrees) every 4 ms while the task executes.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Any

FILE_VERSION = 10011
LOG_COLUMNS = "timestamp,cmdnum,J1,J2,J3,J4,J5,J6"
STRING_FIELD = 32  # bytes every string occupies after its length

OPCODES = {1: "MoveAbsJ", 2: "MoveJ", 3: "MoveL", 4: "MoveC", 5: "WaitTime", 6: "CirPathMode",
           7: "SyncMoveOn", 8: "SyncMoveOff", 50001: "EGMRunJoint", 50002: "EGMRunPose", 50003: "EGMMoveL",
           50004: "EGMMoveC"}


class ProgramError(ValueError):
    """The file is not a motion program the RAPID module accepts: ``errname`` is the RAPID error
    it raises (``ERR_FILESIZE``, ``ERR_INVALID_MP_VERSION``, ``ERR_INVALID_MP_FILE``,
    ``ERR_INVALID_OPCODE``)."""

    def __init__(self, errname: str, message: str) -> None:
        super().__init__(message)
        self.errname = errname


@dataclass(frozen=True)
class Pose:
    trans: tuple[float, float, float]  # mm
    rot: tuple[float, float, float, float]  # q1..q4 = w, x, y, z


@dataclass(frozen=True)
class LoadData:
    mass: float  # kg
    cog: tuple[float, float, float]  # mm, in the tool0 frame
    aom: tuple[float, float, float, float]
    inertia: tuple[float, float, float]  # kg·m²


@dataclass(frozen=True)
class ToolData:
    robhold: bool
    tframe: Pose
    tload: LoadData


@dataclass(frozen=True)
class WobjData:
    robhold: bool
    ufprog: bool
    ufmec: str
    uframe: Pose
    oframe: Pose


@dataclass(frozen=True)
class RobTarget:
    pose: Pose
    robconf: tuple[float, float, float, float]
    extax: tuple[float, ...]


@dataclass(frozen=True)
class SpeedData:
    v_tcp: float  # mm/s
    v_ori: float  # deg/s
    v_leax: float
    v_reax: float


@dataclass(frozen=True)
class ZoneData:
    finep: bool
    pzone_tcp: float  # mm
    pzone_ori: float
    pzone_eax: float
    zone_ori: float
    zone_leax: float
    zone_reax: float


@dataclass(frozen=True)
class Command:
    """One command: its number, its RAPID name and its decoded parameters."""

    cmd_num: int
    name: str
    params: dict[str, Any]


@dataclass
class MotionProgram:
    tool: ToolData
    wobj: WobjData
    gripload: LoadData
    timestamp: str
    seqno: int
    egm_mode: int  # 0 stream only, 1 joint target, 2 pose target, 3 path correction
    commands: list[Command] = field(default_factory=list)
    truncated: bool = False  # the file ended inside a command (the program stops there)


class _Reader:
    """``try_motion_program_read_*`` on a byte string: each read returns None at the end of the file."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.offset = 0

    def num(self) -> float | None:
        if self.offset + 4 > len(self.data):
            self.offset = len(self.data)
            return None
        (value,) = struct.unpack_from("<f", self.data, self.offset)
        self.offset += 4
        return float(value)

    def nums(self, n: int) -> list[float] | None:
        values = [self.num() for _ in range(n)]
        return None if any(v is None for v in values) else [float(v) for v in values if v is not None]

    def string(self) -> str | None:
        length = self.num()
        if length is None or self.offset + STRING_FIELD > len(self.data):
            return None
        raw = self.data[self.offset:self.offset + int(length)]
        self.offset += STRING_FIELD
        return raw.decode("ascii", errors="replace")

    def pose(self) -> Pose | None:
        v = self.nums(7)
        return None if v is None else Pose((v[0], v[1], v[2]), (v[3], v[4], v[5], v[6]))

    def loaddata(self) -> LoadData | None:
        v = self.nums(11)
        return None if v is None else LoadData(v[0], (v[1], v[2], v[3]), (v[4], v[5], v[6], v[7]), (v[8], v[9], v[10]))

    def tooldata(self) -> ToolData | None:
        robhold, tframe, tload = self.num(), self.pose(), self.loaddata()
        if robhold is None or tframe is None or tload is None:
            return None
        return ToolData(robhold != 0, tframe, tload)

    def wobjdata(self) -> WobjData | None:
        robhold, ufprog, ufmec = self.num(), self.num(), self.string()
        uframe, oframe = self.pose(), self.pose()
        if robhold is None or ufprog is None or ufmec is None or uframe is None or oframe is None:
            return None
        return WobjData(robhold != 0, ufprog != 0, ufmec.strip(), uframe, oframe)

    def robtarget(self) -> RobTarget | None:
        v = self.nums(17)
        if v is None:
            return None
        return RobTarget(Pose((v[0], v[1], v[2]), (v[3], v[4], v[5], v[6])), (v[7], v[8], v[9], v[10]), tuple(v[11:]))

    def speeddata(self) -> SpeedData | None:
        v = self.nums(4)
        return None if v is None else SpeedData(*v)

    def zonedata(self) -> ZoneData | None:
        v = self.nums(7)
        return None if v is None else ZoneData(v[0] != 0, *v[1:])


# Parameters of each opcode, in file order: (name, reader method) pairs.
_PARAMETERS: dict[int, tuple[tuple[str, str], ...]] = {
    1: (("joints", "jointtarget"), ("speed", "speeddata"), ("zone", "zonedata")),
    2: (("target", "robtarget"), ("speed", "speeddata"), ("zone", "zonedata")),
    3: (("target", "robtarget"), ("speed", "speeddata"), ("zone", "zonedata")),
    4: (("via", "robtarget"), ("target", "robtarget"), ("speed", "speeddata"), ("zone", "zonedata")),
    5: (("seconds", "num"),),
    6: (("switch", "num"),),
    7: (),
    8: (),
    50001: (("cond_time", "num"), ("ramp_in", "num"), ("ramp_out", "num")),
    50002: (("cond_time", "num"), ("ramp_in", "num"), ("ramp_out", "num"), ("offset", "pose")),
    50003: (("target", "robtarget"), ("speed", "speeddata"), ("zone", "zonedata")),
    50004: (("via", "robtarget"), ("target", "robtarget"), ("speed", "speeddata"), ("zone", "zonedata")),
}
# Numbers that follow the EGM mode in the header (motion_program_exec_egm.mod).
_EGM_CONFIG_NUMS = {0: 0, 1: 14, 2: 30, 3: 7}


def decode_program(data: bytes) -> MotionProgram:
    """Decode a motion program file the way the RAPID module reads it.

    Raises
    ------
    ProgramError
        Where the module raises a RAPID error (a short or foreign header, an unknown opcode).
    """
    reader = _Reader(data)
    version = reader.num()
    if version is None:
        raise ProgramError("ERR_FILESIZE", "the motion program file is empty")
    if int(round(version)) != FILE_VERSION:
        raise ProgramError("ERR_INVALID_MP_VERSION", f"Invalid motion program file version {version:g}")
    tool = reader.tooldata()
    wobj = reader.wobjdata() if tool is not None else None
    gripload = reader.loaddata() if wobj is not None else None
    timestamp = reader.string() if gripload is not None else None
    seqno = reader.num() if timestamp is not None else None
    egm_mode = reader.num() if seqno is not None else None
    if tool is None or wobj is None or gripload is None or timestamp is None or seqno is None or egm_mode is None:
        raise ProgramError("ERR_INVALID_MP_FILE", "the motion program header is incomplete")
    mode = int(round(egm_mode))
    if mode not in _EGM_CONFIG_NUMS or reader.nums(_EGM_CONFIG_NUMS[mode]) is None:
        raise ProgramError("ERR_INVALID_OPCODE" if mode not in _EGM_CONFIG_NUMS else "ERR_INVALID_MP_FILE",
                           f"invalid EGM configuration {egm_mode:g}")
    program = MotionProgram(tool, wobj, gripload, timestamp, int(round(seqno)), mode)
    while True:
        cmd_num, opcode = reader.num(), reader.num()
        if cmd_num is None or opcode is None:
            return program
        op = int(round(opcode))
        if op == 0:  # MOTION_PROGRAM_CMD_NOOP
            continue
        if op not in _PARAMETERS:
            raise ProgramError("ERR_INVALID_OPCODE", f"invalid motion program opcode {opcode:g}")
        params: dict[str, Any] = {}
        for name, kind in _PARAMETERS[op]:
            value = reader.nums(12) if kind == "jointtarget" else getattr(reader, kind)()
            if value is None:
                program.truncated = True
                return program
            params[name] = value
        program.commands.append(Command(int(round(cmd_num)), OPCODES[op], params))


def log_header(timestamp: str) -> bytes:
    """The joint log's header as ``motion_program_log_open`` packs it."""
    stamp, columns = timestamp.encode("ascii"), LOG_COLUMNS.encode("ascii")
    return (struct.pack("<ff", FILE_VERSION, len(stamp)) + stamp + struct.pack("<f", len(columns)) + columns)


def log_row(clock: float, cmd_num: float, joints_deg: list[float]) -> bytes:
    """One row of the joint log (``motion_program_log_data``)."""
    return struct.pack("<8f", clock, cmd_num, *joints_deg)
