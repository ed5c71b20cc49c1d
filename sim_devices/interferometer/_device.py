"""The head's firmware: a 1 kHz sample clock that reads the head, frames the samples, answers
commands and takes faults from the ``FaultPlan``, sending everything to its transports.

Every ``status_rate`` tick the clock thread asks the environmental unit for the air and sets the
head's refraction ratio; every ``environment_rate`` tick it sends the unit's two frames (air, then
material) with one cycle counter.

Commands received by a transport are queued and executed by the clock thread just before the next
sample, and the reply is sent before that sample: every displacement frame after a datum reply is
relative to the new datum.

Every frame carries the time a receiver on the bus would stamp on it (``CanBusTiming``: the clock
thread's actual send time plus the receiving kernel's latency, never closer to the previous frame
than the bus can carry them); socketcand forwards that stamp, as the real daemon forwards the kernel's.

Faults (``FaultKind``, params with defaults; a fault armed with ``count=-1`` fires at every tick
until cleared):

- ``beam_break`` [seconds=0.2]: the beam is blocked; samples say beam not OK, the count is lost
  (datum not set until the host sends a new datum).
- ``stall`` [seconds=0.5]: the head stops producing frames (its counter stops too).
- ``drop_reply`` [frames=5]: the next frames are produced but never sent (a counter gap).
- ``bad_crc`` [frames=1]: the next frames carry a wrong CRC.
- ``garbage`` [size=16]: bytes that are not protocol text on every transport (socketcand:
  non-ASCII; slcan: junk ended by CR).
- ``disconnect`` [seconds=0.0 for socketcand, 0.2 for slcan; transport=None (all)]: socketcand
  closes every client connection and refuses new ones for ``seconds``; slcan unplugs the pty and
  re-plugs a fresh one at the same path after ``seconds``.
- ``delay`` [seconds=0.3; transport=None (all)]: the transport holds every frame for ``seconds``,
  then sends them all at once with their receive timestamps (a congested link, a busy socketcand
  host, a USB adapter that stops being polled); the head keeps sampling, nothing is lost.
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Protocol

import numpy as np

from sim_devices.faults import FaultKind, FaultPlan
from sim_devices.interferometer import _frames
from sim_devices.interferometer._bus import CanBusTiming
from sim_devices.interferometer._config import InterferometerTwinConfig
from sim_devices.interferometer._environment import EnvironmentUnit
from sim_devices.interferometer._head import InterferometerHead

FEED_FAULTS = (FaultKind.BEAM_BREAK, FaultKind.STALL, FaultKind.DROP_REPLY, FaultKind.BAD_CRC,
               FaultKind.GARBAGE, FaultKind.DISCONNECT, FaultKind.DELAY)
BATCH = 0.01  # s: how far past a due sample the head's clock thread sleeps (see _run)


class Transport(Protocol):
    def send_frame(self, can_id: int, data: bytes, timestamp: float) -> None: ...

    def send_garbage(self, junk: bytes) -> None: ...

    def disconnect(self, seconds: float) -> None: ...

    def hold(self, seconds: float) -> None: ...

    def flush(self) -> None:
        """Hand over the frames sent since the last flush (the clock thread flushes once per batch)."""


class InterferometerDevice:
    def __init__(self, head: InterferometerHead, environment: EnvironmentUnit, config: InterferometerTwinConfig,
                 faults: FaultPlan, junk_rng: np.random.Generator, timing_rng: np.random.Generator) -> None:
        self.head = head
        self.environment = environment
        self.config = config
        self.layout = config.layout
        self.faults = faults
        self._junk_rng = junk_rng
        self.timing = CanBusTiming(timing_rng, config.can_bitrate, config.rx_latency)
        self._origin_mono, self._origin_epoch = time.monotonic(), time.time()
        self.transports: dict[str, Transport] = {}
        self._commands: queue.SimpleQueue[tuple[int, bytes]] = queue.SimpleQueue()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._stats_lock = threading.Lock()
        self.stats = dict.fromkeys(("produced", "sent", "dropped", "bad_crc", "garbage", "late_skipped",
                                    "stalled_ticks", "commands", "disconnects", "delays",
                                    "environment_cycles"), 0)
        self._drop_frames = 0
        self._bad_crc_frames = 0
        self._stall_until = 0.0
        self._counter = 0
        self._heartbeat = 0
        self._environment_cycle = 0
        self._on_bus_at: float | None = None  # monotonic time of the tick being sent (None: now)

    # ------------------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="interferometer head clock", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None

    def on_command(self, can_id: int, data: bytes) -> None:
        """Called by a transport for every frame the host puts on the bus."""
        if can_id == self.layout.command_id:
            self._commands.put((can_id, bytes(data)))

    # ------------------------------------------------------------------------------ clock thread
    def _run(self) -> None:
        period = 1.0 / self.layout.sample_rate
        status_every = max(1, round(self.layout.sample_rate / self.layout.status_rate))
        environment_every = max(1, round(self.layout.sample_rate / self.layout.environment_rate))
        origin_mono = time.monotonic()
        tick = 0
        while not self._stop.is_set():
            due = origin_mono + tick * period
            now = time.monotonic()
            if due > now:
                # Past the next sample by one batch: the samples due meanwhile go out together, each
                # stamped with its own time on the bus, in one write per transport (a Python thread
                # waking at 1 kHz costs a tenth of a core, and so does a client woken for every
                # frame; a socketcand daemon forwards the frames its kernel queued in bursts anyway).
                self._flush()
                time.sleep(due - now + BATCH)
                continue
            if now - due > self.config.max_catch_up:  # far behind (host starved): these samples are lost
                skipped = int((now - due) / period)
                tick += skipped
                self._counter = (self._counter + skipped) & 0xFF
                self._count("late_skipped", skipped)
                continue
            self._on_bus_at = None  # a reply goes out now: never stamped before its command came
            self._execute_commands()
            self._on_bus_at = due
            self._take_faults(due)
            if due < self._stall_until:
                self._count("stalled_ticks")
                tick += 1
                continue
            if tick % status_every == 0:
                self.head.refraction_ratio = self.environment.refraction_ratio(self.environment.conditions())
            self._sample(due)
            if tick % status_every == 0:
                self._send_status(due)
            if tick % environment_every == 0:
                self._send_environment()
            tick += 1
        self._flush()

    def _sample(self, now: float) -> None:
        reading = self.head.read(now)
        status = 0
        counts = round(reading.displacement / self.layout.resolution)
        if reading.beam_ok:
            status |= _frames.BEAM_OK
        if reading.signal < self.config.low_signal:
            status |= _frames.SIGNAL_LOW
        if reading.datum_set:
            status |= _frames.DATUM_SET
        if abs(counts) > _frames.INT40_MAX:
            status |= _frames.OVERRANGE
        data = _frames.displacement_frame(self.layout.displacement_id, counts, self._counter, status, reading.signal)
        self._counter = (self._counter + 1) & 0xFF
        self._count("produced")
        if self._drop_frames > 0:
            self._drop_frames -= 1
            self._count("dropped")
            return
        if self._bad_crc_frames > 0:
            self._bad_crc_frames -= 1
            data = data[:7] + bytes([data[7] ^ 0xA5])
            self._count("bad_crc")
        self._broadcast(self.layout.displacement_id, data)
        self._count("sent")

    def _send_status(self, now: float) -> None:
        beam_ok, datum_set, signal = self.head.status(now)
        status = (_frames.BEAM_OK if beam_ok else 0) | (_frames.DATUM_SET if datum_set else 0)
        if signal < self.config.low_signal:
            status |= _frames.SIGNAL_LOW
        data = _frames.status_frame(self.layout.status_id, status, signal, self.head.axis,
                                    self.head.datum_generation, self._heartbeat)
        self._heartbeat = (self._heartbeat + 1) & 0xFF
        self._broadcast(self.layout.status_id, data)

    def _send_environment(self) -> None:
        unit = self.environment
        readings, faulty = unit.read(unit.conditions())
        materials = [readings[name] for name in unit.fitted if name.startswith("material")]
        for can_id, data in _frames.environment_frames(
                self.layout.environment_air_id, self.layout.environment_material_id, self._environment_cycle,
                readings["air_temperature"], readings["pressure"], readings["humidity"], materials, faulty):
            self._broadcast(can_id, data)
        self._environment_cycle = (self._environment_cycle + 1) & 0x0F
        self._count("environment_cycles")

    def _execute_commands(self) -> None:
        while not self._commands.empty():  # checked first: an empty get_nowait raises, at every tick
            try:
                can_id, data = self._commands.get_nowait()
            except queue.Empty:
                return
            parsed = _frames.parse_command(can_id, data)
            if parsed is None:
                continue  # a corrupted command is ignored; the host times out and may retry
            opcode, token = parsed
            self._count("commands")
            if opcode == _frames.OPCODE_DATUM:
                result = 0 if self.head.set_datum() else 1
            elif opcode == _frames.OPCODE_SYNC:
                result = 0  # nothing to do: the reply's place in the stream is the point
            else:
                result = 2  # unknown opcode
            reply = _frames.reply_frame(self.layout.reply_id, opcode, token, result, self.head.datum_generation)
            self._broadcast(self.layout.reply_id, reply)

    def _take_faults(self, now: float) -> None:
        plan = self.faults
        if not plan.armed():  # cheap test first: the clock runs at 1 kHz
            return
        if fault := plan.take(FaultKind.BEAM_BREAK):
            self.head.block_beam(now + float(fault.params.get("seconds", 0.2)))
        if fault := plan.take(FaultKind.STALL):
            self._stall_until = max(self._stall_until, now + float(fault.params.get("seconds", 0.5)))
        if fault := plan.take(FaultKind.DROP_REPLY):
            self._drop_frames += int(fault.params.get("frames", 5))
        if fault := plan.take(FaultKind.BAD_CRC):
            self._bad_crc_frames += int(fault.params.get("frames", 1))
        if fault := plan.take(FaultKind.GARBAGE):
            self._send_garbage(int(fault.params.get("size", 16)))
        if fault := plan.take(FaultKind.DISCONNECT):
            wanted = fault.params.get("transport")
            for name, transport in self.transports.items():
                if wanted in (None, name):
                    default = 0.0 if name == "socketcand" else 0.2
                    transport.disconnect(float(fault.params.get("seconds", default)))
            self._count("disconnects")
        if fault := plan.take(FaultKind.DELAY):
            wanted = fault.params.get("transport")
            for name, transport in self.transports.items():
                if wanted in (None, name):
                    transport.hold(float(fault.params.get("seconds", 0.3)))
            self._count("delays")

    def _send_garbage(self, size: int) -> None:
        junk = self._junk_rng.integers(0x80, 0x100, max(1, size), dtype=int).astype("uint8").tobytes()
        self._flush()  # the frames before the junk go out before it
        for name, transport in self.transports.items():
            # socketcand: bytes that are not ASCII; slcan: the same, ended by CR like a frame line.
            transport.send_garbage(junk if name == "socketcand" else junk + b"\r")
        self._count("garbage")

    def _broadcast(self, can_id: int, data: bytes) -> None:
        # The frame goes on the bus at its sample's time (epoch, immune to clock steps), never earlier
        # than the frame before it (the bus timing keeps them apart).
        at = self._on_bus_at if self._on_bus_at is not None else time.monotonic()
        sent = self._origin_epoch + (at - self._origin_mono)
        stamp = self.timing.receive_time(sent, len(data))
        for transport in self.transports.values():
            transport.send_frame(can_id, data, stamp)

    def _flush(self) -> None:
        for transport in self.transports.values():
            transport.flush()

    def _count(self, key: str, amount: int = 1) -> None:
        with self._stats_lock:
            self.stats[key] += amount

    def snapshot(self) -> dict:
        with self._stats_lock:
            return dict(self.stats)
