"""The rotary table's Modbus face: a pymodbus 3.16 ``SimDevice`` whose async action is the drive.

pymodbus 3.16 ignores datastore subclasses; the supported hook is ``SimDevice(action=...)``, an async
function run before every read and write. Ours advances the table physics, refreshes the read-only
registers (alarm, status, encoder, actual velocity), executes writes to the velocity, acceleration
and control registers, and answers an armed ``exception`` fault with that Modbus exception code.

Exception codes, as the Modbus application protocol defines them:

- 2 (illegal data address): an unmapped address, or a write to a read-only register (``SimData``);
- 3 (illegal data value): a value the drive never accepts: a speed or acceleration word of 0 or
  above the drive's maximum, an unknown opcode, a move whose target lies beyond the soft limits
  (the offending write is the opcode that would start it; nothing moves and no alarm is latched);
- 4 (server device failure): the drive cannot act now: alarm present, servo off, not referenced.

Device ids: on RTU the drive answers only its own ``unit``, stays silent for every other address,
and executes broadcast (id 0) writes without replying, as a real RTU slave does. On TCP the unit id
is redundant (the IP address names the device); like a direct TCP device it also answers 0 and 255
for itself, and answers exception 11 (gateway target failed to respond) for any other id.

Transport faults (dropped reply, delay, garbage, truncation, bad CRC, stall, disconnect) are not
taken here but in the relay in front of the server (``sim_devices._pty``), one plan per endpoint.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Coroutine, Mapping
from typing import Any, TypeVar, cast

from pymodbus.constants import ExcCodes
from pymodbus.exceptions import NoSuchIdException
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice
from pymodbus.simulator.simcore import SimCore

from sim_devices._pty import PtyRelay, modbus_rtu_reply_framer, modbus_tcp_reply_framer
from sim_devices.faults import FaultKind, FaultPlan
from sim_devices.rotary_table._physics import CommandRefused, TablePhysics, ValueRefused
from sim_devices.rotary_table._register_map import DriveRegisterMap
from sim_devices.rotary_table._tcp_proxy import TcpFaultProxy

_T = TypeVar("_T")

BROADCAST = 0
TCP_DIRECT_IDS = (0, 255)  # Modbus TCP implementation guide: a directly connected device answers these too


class _DriveCore(SimCore):
    """The server's datastore with real device-id rules: only ``aliases`` reach the drive.

    pymodbus 3.16's ``SimCore`` hands a request for an unknown id to a KeyError, which the server
    turns into exception 4; raising ``NoSuchIdException`` instead makes the server answer exception
    11, or nothing at all when it was built with ``ignore_missing_devices=True`` (RTU).
    """

    def __init__(self, device: SimDevice, aliases: Mapping[int, int]) -> None:
        super().__init__(device)
        self._aliases = dict(aliases)

    def _drive_id(self, device_id: int) -> int:
        try:
            return self._aliases[device_id]
        except KeyError:
            raise NoSuchIdException(f"device id {device_id}") from None

    async def async_getValues(self, device_id: int, func_code: int, address: int,
                              count: int = 1) -> list[int] | list[bool] | ExcCodes:
        return await super().async_getValues(self._drive_id(device_id), func_code, address, count)

    async def async_setValues(self, device_id: int, func_code: int, address: int,
                              values: list[int] | list[bool]) -> ExcCodes | None:
        return await super().async_setValues(self._drive_id(device_id), func_code, address, values)


def _corrupt_mbap(reply: bytes) -> bytes:
    """Modbus TCP has no CRC: a "bad CRC" answer is a corrupted MBAP header (wrong protocol id)."""
    return reply[:2] + b"\xa5\x5a" + reply[4:] if len(reply) >= 4 else reply


class ModbusDrive:
    """Register image of the drive, kept in step with the physics by the SimDevice action."""

    def __init__(self, physics: TablePhysics, register_map: DriveRegisterMap, faults: FaultPlan, unit: int = 1) -> None:
        self.physics = physics
        self.map = register_map
        self.faults = faults
        self.unit = unit
        self._scale = register_map.counts_per_rev / physics.config.counts_per_rev
        self.requests = 0

    def device(self) -> SimDevice:
        read_only = {"alarm", "status", "encoder_position", "actual_velocity"}
        # DriveRegisterMap refuses overlapping spans, so the layout is always well formed.
        simdata = [SimData(address=start, count=width, values=0, datatype=DataType.REGISTERS,
                           readonly=name in read_only)
                   for name, (start, width) in self.map.spans().items()]
        return SimDevice(id=self.unit, simdata=simdata, action=self.action)

    def datastore(self, aliases: tuple[int, ...] = ()) -> SimCore:
        """The datastore a server serves: this drive under ``unit`` and the ids in ``aliases``."""
        return _DriveCore(self.device(), {self.unit: self.unit, **dict.fromkeys(aliases, self.unit)})

    # ----------------------------------------------------------------------------- the action
    async def action(self, function_code: int, start_address: int, address: int, count: int,
                     registers: list[int], set_values: list[int] | list[bool] | None) -> ExcCodes | None:
        self.requests += 1
        fault = self.faults.take(FaultKind.EXCEPTION)
        if fault is not None:
            return ExcCodes(int(fault.params.get("code", ExcCodes.DEVICE_FAILURE)))
        if set_values is not None:
            result = self._write(start_address, address, registers, [int(v) for v in set_values])
            if result is not None:
                self._refresh(start_address, registers)
                return result
        self._refresh(start_address, registers)
        return None

    def _write(self, start: int, address: int, registers: list[int], values: list[int]) -> ExcCodes | None:
        m = self.map
        written = dict(zip(range(address, address + len(values)), values))

        def current(reg: int) -> int:  # the value after this write lands
            return written.get(reg, registers[reg - start])

        config = self.physics.config
        try:
            # A setting word is accepted from 1 up to the word the drive itself reads back at its
            # maximum (which may round above it: 2 rad/s² reads as 2 × 1/6 rev/s²); the value is then
            # capped at the physical maximum, so every word read back can be written back.
            if m.velocity in written:
                word = current(m.velocity)
                self._check_word("velocity", word, m.speed_word(config.max_speed))
                self.physics.set_speed(min(m.speed_of_word(word), config.max_speed))
            if m.acceleration in written:
                word = current(m.acceleration)
                self._check_word("acceleration", word, m.acceleration_word(config.acceleration))
                self.physics.set_acceleration(min(m.acceleration_of_word(word), config.acceleration))
            if m.control in written:
                target = m.s32_of_words(current(m.position_command), current(m.position_command + 1))
                self._execute(written[m.control], target)
        except ValueRefused:
            return ExcCodes.ILLEGAL_VALUE
        except CommandRefused:
            return ExcCodes.DEVICE_FAILURE
        return None

    @staticmethod
    def _check_word(name: str, word: int, largest: int) -> None:
        if not 1 <= word <= largest:
            raise ValueRefused(f"{name} word {word} outside 1..{largest}")

    def _execute(self, opcode: int, position_command: int) -> None:
        ops, physics = self.map.opcodes, self.physics
        counts = int(round(position_command / self._scale))
        if opcode == ops.move_absolute:
            physics.move_to_counts(counts)
        elif opcode == ops.move_relative:
            physics.move_by_counts(counts)
        elif opcode == ops.home:
            physics.home()
        elif opcode == ops.stop:
            physics.stop()
        elif opcode == ops.enable:
            physics.enable(True)
        elif opcode == ops.disable:
            physics.enable(False)
        elif opcode == ops.alarm_reset:
            physics.alarm_reset()
        elif opcode != 0:
            raise ValueRefused(f"unknown opcode 0x{opcode:02x}")

    def _refresh(self, start: int, registers: list[int]) -> None:
        m, bits = self.map, self.map.status_bits
        status = self.physics.status()
        counts = int(round(self.physics.read_counts() * self._scale))
        word = 0
        for name in ("enabled", "moving", "stopping", "homing", "homed", "in_position"):
            if status[name]:
                word |= 1 << getattr(bits, name)
        alarm_word = 0
        for alarm in status["alarms"]:
            alarm_word |= 1 << getattr(m.alarm_bits, alarm, m.alarm_bits.encoder_fault)
        if alarm_word:
            word |= (1 << bits.alarm) | (1 << bits.drive_fault)
        registers[m.alarm - start] = alarm_word
        registers[m.status - start] = word
        first, second = m.words_of_s32(counts)
        registers[m.encoder_position - start] = first
        registers[m.encoder_position + 1 - start] = second
        registers[m.actual_velocity - start] = m.actual_velocity_word(status["velocity"])
        registers[m.velocity - start] = m.speed_word(self.physics.speed)
        registers[m.acceleration - start] = m.acceleration_word(self.physics.acceleration)


class _LoopThread:
    """An asyncio loop in a daemon thread (pymodbus servers need a running loop)."""

    def __init__(self, name: str) -> None:
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name=name, daemon=True)
        self._thread.start()

    def run(self, coro: Coroutine[Any, Any, _T], timeout: float = 10.0) -> _T:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def close(self) -> None:
        async def _cancel_rest() -> None:
            tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

        try:
            self.run(_cancel_rest(), 5.0)
        except Exception:
            pass
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(5.0)
        if not self._thread.is_alive():
            self.loop.close()


class ModbusTableTwin:
    """Modbus TCP and/or RTU server of one drive, each behind its own fault relay.

    ``faults`` (TCP) and ``rtu_faults`` are separate ``FaultPlan`` objects so that a fault armed for
    one transport is never taken by the other. ``start()`` returns the endpoints.
    """

    def __init__(self, physics: TablePhysics, register_map: DriveRegisterMap | Mapping[str, Any] | None = None, *,
                 unit: int = 1, tcp: bool = True, rtu: bool = True, tcp_port: int = 0, seed: int = 0) -> None:
        self.map = DriveRegisterMap.from_config(register_map)
        self.faults = FaultPlan()  # TCP
        self.rtu_faults = FaultPlan()
        self.tcp_drive = ModbusDrive(physics, self.map, self.faults, unit)
        self.rtu_drive = ModbusDrive(physics, self.map, self.rtu_faults, unit)
        self.unit = unit
        self._want_tcp, self._want_rtu, self._tcp_port, self._seed = tcp, rtu, tcp_port, seed
        self._loop: _LoopThread | None = None
        self._servers: list[Any] = []
        self._proxy: TcpFaultProxy | None = None
        self._relay: PtyRelay | None = None
        self.endpoints: dict[str, Any] = {}

    def start(self) -> dict[str, Any]:
        self._loop = _LoopThread("modbus table twin")
        try:
            if self._want_tcp:
                direct_port = self._loop.run(self._start_tcp())
                self._proxy = TcpFaultProxy(("127.0.0.1", direct_port), self.faults, framer=modbus_tcp_reply_framer,
                                            corrupt=_corrupt_mbap, port=self._tcp_port,
                                            name="modbus tcp fault proxy").start()
                self.endpoints.update(modbus_tcp_port=self._proxy.port, modbus_tcp_direct_port=direct_port)
            if self._want_rtu:
                self._relay = PtyRelay(self.rtu_faults, framer=modbus_rtu_reply_framer, seed=self._seed,
                                       name="modbus rtu relay").start()
                self._loop.run(self._start_rtu(self._relay.device_path))
                self.endpoints.update(modbus_rtu_port=self._relay.host_path)
        except BaseException:
            self.stop()
            raise
        return dict(self.endpoints)

    async def _start_tcp(self) -> int:
        """Start the TCP server on an OS-chosen port; returns that port."""
        server = ModbusTcpServer(self.tcp_drive.device(), address=("127.0.0.1", 0))
        # ``context`` is the server's public datastore attribute; ours applies the device-id rules.
        server.context = self.tcp_drive.datastore(TCP_DIRECT_IDS)
        await server.serve_forever(background=True)
        self._servers.append(server)
        # pymodbus types ``transport`` as a BaseTransport; for a listening server it is the asyncio.Server.
        listener = cast(asyncio.Server, server.transport)
        return int(listener.sockets[0].getsockname()[1])

    async def _start_rtu(self, path: str) -> ModbusSerialServer:
        # An RTU slave is silent for other addresses and executes broadcast writes without a reply.
        server = ModbusSerialServer(self.rtu_drive.device(), port=path, baudrate=115200, timeout=1.0,
                                    ignore_missing_devices=True, broadcast_enable=True)
        server.context = self.rtu_drive.datastore()
        await server.serve_forever(background=True)
        self._servers.append(server)
        return server

    def stop(self) -> None:
        if self._proxy is not None:
            self._proxy.stop()
            self._proxy = None
        if self._loop is not None:
            for server in self._servers:
                try:
                    self._loop.run(server.shutdown(), 5.0)
                except Exception:
                    pass
            self._servers = []
            self._loop.close()
            self._loop = None
        if self._relay is not None:
            self._relay.stop()
            self._relay = None
