"""``CanInterferometer``: the interferometer feed over CAN with python-can (socketcand or slcan).

A background thread receives frames, checks CRC and sample counter, and fills a bounded ring
buffer (``FeedBuffer``). Readers never see a bad value: samples without a valid displacement carry
NaN and a flag, and ``average`` refuses any window with a gap, a rejected frame, a stall, a beam
break or a lost datum. Transport trouble is handled in the thread: garbage is counted as a
``ProtocolError`` and skipped, a lost connection is re-opened every ``reconnect_interval`` seconds
until ``close()``; meanwhile readers get ``DeviceConnectionError``.
"""

from __future__ import annotations

import itertools
import logging
import math
import os
import socket
import threading
import time
from collections import deque
from collections.abc import Iterator, Mapping
from typing import Any

import can

from drivers._errors import DeviceConnectionError, DeviceError, DeviceTimeout, ProtocolError
from drivers.interferometer._environment import EnvironmentTracker, require_usable
from drivers.interferometer._feed import CanSample, FeedBuffer, require_valid
from drivers.interferometer._interface import BeamInterrupted, EnvironmentReading, FeedGap
from drivers.interferometer._layout import (
    COUNTER_MODULUS,
    OPCODE_DATUM,
    OPCODE_SYNC,
    REPLY_DONE,
    ReplyFrame,
    StatusFrame,
    decode_displacement,
    decode_environment_air,
    decode_environment_material,
    decode_reply,
    decode_status,
    encode_command,
)
from drivers.interferometer._settings import SlcanSettings, SocketcandSettings


class _DropSplitFrameWarnings(logging.Filter):
    """python-can's socketcand client logs a warning whenever a TCP read ends mid-frame, which is
    normal on a 1 kHz stream (it waits for the rest); keep its other warnings."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "incomplete message" not in record.getMessage()


logging.getLogger("can.interfaces.socketcand.socketcand").addFilter(_DropSplitFrameWarnings())

_RECV_POLL = 0.05  # s: how long one bus.recv may block, i.e. how fast close() and EOF are noticed
_GARBAGE_BEFORE_REOPEN = 3  # consecutive undecodable reads before the transport is re-opened
_FIRST_READING_CYCLES = 1.5  # measuring cycles environment() waits, right after open, for the first reading


class CanInterferometer:
    """Laser interferometer displacement feed on a CAN bus reached through python-can.

    Parameters
    ----------
    settings : SocketcandSettings or SlcanSettings
        The transport (socketcand daemon or slcan adapter), the ``FrameLayout`` and the receive
        options; their field descriptions say what each does. Two need more words:
        ``open_attempts``: socketcand's handshake fails if a frame arrives in the same read as the
        last ``< ok >``; a retry fixes that. ``stall_timeout``: a silence longer than this between
        two samples is a gap even if the counter is contiguous; it must stay below 256 sample
        periods so the 8-bit counter cannot alias (default 200 periods, 0.2 s at 1 kHz). It is
        measured on the frames' timestamps: the device's clock for socketcand (immune to host
        scheduling hiccups), the host's arrival clock for slcan (a host starved for longer than
        this reports a stall too: conservative, never a wrong value).
    name : str
        Device name used in every error.
    """

    def __init__(self, settings: SocketcandSettings | SlcanSettings, *, name: str = "interferometer") -> None:
        self.name = name
        self.settings = settings
        self.layout = settings.layout
        self.optics = settings.optics
        if isinstance(settings, SocketcandSettings):
            self._transport = "socketcand"
            self._bus_kwargs: dict[str, Any] = {"interface": "socketcand", "host": settings.host,
                                                "port": settings.port, "channel": settings.channel}
        else:
            self._transport = "slcan"
            self._bus_kwargs = {"interface": "slcan", "channel": settings.port, "bitrate": settings.bitrate,
                                "sleep_after_open": 0}
        self.open_timeout = settings.open_timeout
        self.open_attempts = settings.open_attempts
        self.stall_timeout = (settings.stall_timeout if settings.stall_timeout is not None
                              else 200.0 / self.layout.sample_rate)
        self.reconnect_interval = settings.reconnect_interval
        self.command_timeout = settings.command_timeout
        self.sync_before_average = settings.sync_before_average
        self._buffer = FeedBuffer(settings.ring_capacity, name)
        self._buffer.set_failure_probe(self._connection_failure)

        self._bus: can.BusABC | None = None
        self._bus_lock = threading.Lock()  # guards swapping self._bus against send()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._connection_error: DeviceConnectionError | None = None

        # Receive-thread state.
        self._prev_counter: int | None = None
        self._prev_time = 0.0
        self._device_clock = self._transport == "socketcand"  # slcan stamps frames on the host
        self._pending_defect = ""
        self._consecutive_garbage = 0

        self._stats_lock = threading.Lock()
        self._stats = dict.fromkeys(
            ("samples", "gaps", "lost_samples", "stalls", "protocol_errors", "garbage_reads", "reconnects",
             "foreign_frames", "status_frames", "environment_readings", "environment_missed",
             "environment_incomplete"), 0)
        self._protocol_errors: deque[ProtocolError] = deque(maxlen=20)

        self._environment = EnvironmentTracker()
        self._status: StatusFrame | None = None
        self._status_mono = 0.0
        self._reply_cond = threading.Condition()
        self._replies: dict[int, tuple[ReplyFrame, int]] = {}  # token -> (reply, next sample seq)
        self._tokens = itertools.cycle(range(1, 256))
        self._link_epoch = 0  # +1 at every lost connection: a reply can never cross it

    # ------------------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Open the bus (with retries) and start receiving. Raises ``DeviceConnectionError``."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._bus = self._open_bus_with_retries("open")
        self._connection_error = None
        self._thread = threading.Thread(target=self._receive_loop, name=f"{self.name} CAN receive", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(5.0)
        with self._bus_lock:
            bus, self._bus = self._bus, None
        _shutdown(bus)
        self._buffer.wake()

    def __enter__(self) -> CanInterferometer:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------------------ readings
    def latest(self, max_age: float = 0.1) -> CanSample:
        """The newest sample. Raises ``FeedGap`` if it is older than ``max_age`` seconds (host clock),
        ``DeviceConnectionError`` if the connection is down. The sample may have ``beam_ok`` False
        (its displacement is then NaN)."""
        sample, age = self._buffer.newest()
        if sample is None or age > max_age:
            failure = self._connection_failure()
            if failure is not None:
                raise failure
            what = "no sample received yet" if sample is None else f"newest sample is {age:.3f} s old"
            raise FeedGap(self.name, "latest", f"{what} (max_age {max_age} s)")
        return sample

    def latest_valid(self, max_age: float = 0.1) -> CanSample:
        """``latest`` plus the checks of ``average``: beam OK, datum set, not overrange."""
        sample = self.latest(max_age)
        require_valid(self.name, "latest", sample)
        return sample

    def average(self, duration: float, timeout: float | None = None) -> float:
        """Mean displacement (m) over the next ``duration`` seconds, i.e. the next
        ``round(duration * sample_rate)`` samples (at least one).

        Raises ``BeamInterrupted`` (``DatumLost`` if there is no valid datum), ``FeedGap`` (counter gap,
        rejected frame, stall, reconnection or no data), ``DeviceConnectionError``, ``DeviceFault``
        (overrange). Never averages across any of them. ``timeout`` defaults to ``duration + 2`` s.
        """
        if not duration > 0 or not math.isfinite(duration):
            raise ValueError(f"{self.name}: average duration must be a positive number of seconds, got {duration!r}")
        count = max(1, round(duration * self.layout.sample_rate))
        timeout = duration + 2.0 if timeout is None else float(timeout)
        self._require_running("average")
        deadline = time.monotonic() + timeout
        start = self._command(OPCODE_SYNC, "average", timeout)[1] if self.sync_before_average else None
        # Waiting for the next sample: generous, since a real stall is caught by its timestamp jump.
        return self._buffer.average(count, deadline, max(5 * self.stall_timeout, 1.0), "average", start)

    def samples(self, timeout: float = 1.0) -> Iterator[CanSample]:
        """Iterate over every sample from now on (check ``sample.defect`` for discontinuities).
        Raises ``FeedGap`` (or ``DeviceConnectionError``) when none arrives within ``timeout``."""
        self._require_running("samples")
        return self._buffer.stream(timeout, "samples")

    def recent(self, count: int) -> list[CanSample]:
        """Up to ``count`` most recent samples, oldest first."""
        return self._buffer.recent(count)

    def zero(self, timeout: float | None = None) -> None:
        """Set the datum in the head: the current position reads 0 from the next sample on.

        Raises ``BeamInterrupted`` if the head refuses (beam not OK), ``DeviceTimeout`` if it does
        not answer, ``DeviceConnectionError`` if the bus is down."""
        self._require_running("zero")
        reply, first_after = self._command(OPCODE_DATUM, "zero", timeout)
        if reply.result != REPLY_DONE:
            raise BeamInterrupted(self.name, "zero", "the head refused to set the datum: beam not OK")
        # Return once a sample relative to the new datum is in, so latest() agrees with the datum.
        wait = self.command_timeout if timeout is None else float(timeout)
        self._buffer.get(first_after, time.monotonic() + wait, "zero")

    def environment(self, max_age: float | None = None, *, strict: bool = True) -> EnvironmentReading:
        """The newest reading of the environmental unit (air temperature K, pressure Pa, relative
        humidity as a fraction, material temperatures K).

        Parameters
        ----------
        max_age : float, optional
            Seconds (host clock) the reading may be old; default three measuring cycles
            (3 / ``layout.environment_rate``).
        strict : bool
            True (default): ``DeviceFault`` when a sensor reports a fault or an air sensor gives no
            reading. False: such a reading is returned, NaN where there is no value, the faulty
            sensors named in ``faults``.

        Raises
        ------
        FeedGap
            No reading yet (after waiting up to 1.5 measuring cycles for the first one since
            ``open``), or the newest is older than ``max_age``.
        DeviceConnectionError
            The feed is closed or the connection is down.
        DeviceFault
            See ``strict``.
        """
        limit = 3.0 / self.layout.environment_rate if max_age is None else float(max_age)
        reading, age = self._environment.newest()
        if reading is None and self._connection_failure() is None:
            # Just opened: the unit sends a reading once per measuring cycle, so the first one is at
            # most a cycle away; wait for it (bounded) rather than fail a run's first step on it.
            self._environment.wait_first(_FIRST_READING_CYCLES / self.layout.environment_rate)
            reading, age = self._environment.newest()
        if reading is None or age > limit:
            failure = self._connection_failure()
            if failure is not None:
                raise failure
            what = ("no environmental reading received yet" if reading is None
                    else f"newest environmental reading is {age:.2f} s old")
            raise FeedGap(self.name, "environment", f"{what} (max_age {limit:g} s)")
        if strict:
            require_usable(self.name, "environment", reading)
        return reading

    # ------------------------------------------------------------------------------ health
    def stats(self) -> dict[str, Any]:
        """Counters since ``open``: samples, gaps, lost_samples, stalls, protocol_errors,
        garbage_reads, reconnects, foreign_frames, status_frames, environment_readings,
        environment_missed (cycles missing between two readings), environment_incomplete (a material
        frame without its cycle's air frame); plus transport, connected and the last errors."""
        with self._stats_lock:
            out: dict[str, Any] = dict(self._stats)
            out["last_protocol_error"] = str(self._protocol_errors[-1]) if self._protocol_errors else None
        out["transport"] = self._transport
        out["connected"] = self._bus is not None and self._thread is not None
        out["connection_error"] = str(self._connection_error) if self._connection_error else None
        return out

    def protocol_errors(self) -> list[ProtocolError]:
        """The most recent (up to 20) protocol errors, oldest first."""
        with self._stats_lock:
            return list(self._protocol_errors)

    def status(self, max_age: float = 1.0) -> StatusFrame:
        """The head's latest heartbeat (aimed axis, signal strength, datum generation)."""
        status, age = self._status, time.monotonic() - self._status_mono
        if status is None or age > max_age:
            cause = f"no heartbeat frame within the last {max_age} s" if status else "no heartbeat frame received yet"
            raise FeedGap(self.name, "status", cause)
        return status

    # ------------------------------------------------------------------------------ internals
    def _require_running(self, operation: str) -> None:
        if self._thread is None:
            raise DeviceConnectionError(self.name, operation, "the feed is not open (call open() first)")

    def _connection_failure(self) -> Exception | None:
        if self._thread is None:
            return DeviceConnectionError(self.name, "read", "the feed is closed")
        return self._connection_error

    def _command(self, opcode: int, operation: str, timeout: float | None) -> tuple[ReplyFrame, int]:
        """Send a command; return the reply and the sequence number of the first sample after it."""
        token = next(self._tokens)
        data = encode_command(self.layout.command_id, opcode, token)
        message = can.Message(arbitration_id=self.layout.command_id, data=data, is_extended_id=False)
        with self._reply_cond:
            self._replies.pop(token, None)
        with self._bus_lock:
            bus, epoch = self._bus, self._link_epoch
            if bus is None:
                raise self._connection_error or DeviceConnectionError(self.name, operation, "bus not open")
            try:
                bus.send(message)
            except (can.CanError, OSError, ValueError) as exc:
                raise DeviceConnectionError(self.name, operation, f"could not send the command: {exc}") from exc
        deadline = time.monotonic() + (self.command_timeout if timeout is None else float(timeout))
        with self._reply_cond:
            while token not in self._replies:
                if self._link_epoch != epoch:
                    raise DeviceConnectionError(self.name, operation, "connection lost while waiting for the "
                                                f"reply to command 0x{opcode:02X}")
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    failure = self._connection_failure()
                    if failure is not None:
                        raise failure
                    raise DeviceTimeout(self.name, operation, f"no reply to command 0x{opcode:02X} within "
                                        f"{self.command_timeout if timeout is None else timeout} s")
                self._reply_cond.wait(remaining)
            return self._replies.pop(token)

    def _open_bus_with_retries(self, operation: str) -> can.BusABC:
        last: DeviceError | None = None
        for attempt in range(self.open_attempts):
            if self._stop.is_set():
                break
            try:
                return self._open_bus_once(operation)
            except DeviceError as exc:
                last = exc
                self._stop.wait(min(0.1 * 2**attempt, 1.0))
        raise DeviceConnectionError(self.name, operation, f"could not open the {self._transport} bus after "
                                    f"{self.open_attempts} attempt(s): {last.cause if last else 'stopped'}")

    def _open_bus_once(self, operation: str) -> can.BusABC:
        kwargs = self._bus_kwargs
        if self._transport == "socketcand":
            # python-can's client retries a refused connect for 10 s and then blocks in recv() without
            # a timeout; check the daemon greets us before handing it the connection.
            _probe_socketcand(self.name, operation, kwargs["host"], kwargs["port"], self.open_timeout)
        elif not os.path.exists(kwargs["channel"]):
            raise DeviceConnectionError(self.name, operation, f"serial port {kwargs['channel']} does not exist")
        return _open_with_watchdog(self.name, operation, kwargs, self.open_timeout)

    def _receive_loop(self) -> None:
        while not self._stop.is_set():
            bus = self._bus
            if bus is None:
                self._try_reconnect()
                continue
            try:
                message = bus.recv(timeout=_RECV_POLL)
            except Exception as exc:  # python-can raises CanError, slcan also bare ValueError on bad hex
                self._on_receive_error(bus, exc)
                continue
            if message is None:
                if not _transport_alive(bus):
                    self._connection_lost(bus, "the server closed the connection")
                continue
            self._consecutive_garbage = 0
            self._on_message(message)

    def _on_message(self, message: can.Message) -> None:
        if message.is_error_frame or message.is_remote_frame or message.is_extended_id:
            self._count("foreign_frames")
            return
        can_id, data = message.arbitration_id, bytes(message.data)
        layout = self.layout
        try:
            if can_id == layout.displacement_id:
                self._on_displacement(message, decode_displacement(self.name, can_id, data))
            elif can_id == layout.status_id:
                self._status, self._status_mono = decode_status(self.name, can_id, data), time.monotonic()
                self._count("status_frames")
            elif can_id == layout.reply_id:
                reply = decode_reply(self.name, can_id, data)
                with self._reply_cond:
                    self._replies[reply.token] = (reply, self._buffer.next_seq)
                    self._reply_cond.notify_all()
            elif can_id == layout.environment_air_id:
                self._environment.on_air(decode_environment_air(self.name, can_id, data))
            elif can_id == layout.environment_material_id:
                frame = decode_environment_material(self.name, can_id, data)
                complete, missed = self._environment.on_material(frame, float(message.timestamp))
                self._count("environment_readings" if complete else "environment_incomplete")
                self._count("environment_missed", missed)
            else:
                self._count("foreign_frames")
        except ProtocolError as exc:
            self._protocol_error(exc)

    def _on_displacement(self, message: can.Message, frame) -> None:
        now = float(message.timestamp) if self._device_clock else time.monotonic()
        defects = [self._pending_defect] if self._pending_defect else []
        if self._prev_counter is not None:
            missing = (frame.counter - self._prev_counter - 1) % COUNTER_MODULUS
            silence = now - self._prev_time
            if missing:
                defects.append(f"{missing} sample(s) missing (counter {self._prev_counter} -> {frame.counter})")
                self._count("lost_samples", missing)
            elif silence > self.stall_timeout:
                defects.append(f"no sample for {silence:.3f} s (feed stalled)")
                self._count("stalls")
            if defects:
                self._count("gaps")
        self._pending_defect = ""
        self._prev_counter, self._prev_time = frame.counter, now
        valid = frame.beam_ok and frame.datum_set and not frame.overrange
        sample = CanSample(
            timestamp=float(message.timestamp),
            displacement=frame.counts * self.layout.resolution if valid else math.nan,
            beam_ok=frame.beam_ok,
            signal_strength=frame.signal_strength,
            counter=frame.counter,
            received=time.time(),
            datum_set=frame.datum_set,
            signal_low=frame.signal_low,
            overrange=frame.overrange,
            defect="; ".join(defects),
        )
        self._count("samples")
        self._buffer.push(sample)

    def _on_receive_error(self, bus: can.BusABC, exc: Exception) -> None:
        if _is_garbage(exc):
            self._count("garbage_reads")
            self._protocol_error(ProtocolError(self.name, "receive", f"undecodable data on the bus: {exc}"))
            self._consecutive_garbage += 1
            if self._consecutive_garbage >= _GARBAGE_BEFORE_REOPEN:
                # socketcand's client keeps unparsable text in its buffer and fails on it forever.
                self._connection_lost(bus, f"{self._consecutive_garbage} undecodable reads in a row")
            elif hasattr(bus, "flush"):
                try:
                    bus.flush()  # slcan keeps undecodable bytes in its line buffer otherwise
                except Exception:
                    pass
            return
        self._connection_lost(bus, f"receive failed: {exc}")

    def _protocol_error(self, exc: ProtocolError) -> None:
        with self._stats_lock:
            self._stats["protocol_errors"] += 1
            self._protocol_errors.append(exc)
        self._pending_defect = f"frame(s) rejected ({exc.cause})"

    def _connection_lost(self, bus: can.BusABC, cause: str) -> None:
        with self._bus_lock:
            if self._bus is bus:
                self._bus = None
            self._link_epoch += 1
        _shutdown(bus)
        with self._reply_cond:
            self._reply_cond.notify_all()
        self._connection_error = DeviceConnectionError(self.name, "receive", f"connection lost: {cause}")
        self._pending_defect = "connection lost and re-opened"
        self._buffer.wake()

    def _try_reconnect(self) -> None:
        try:
            bus = self._open_bus_once("reconnect")
        except DeviceError as exc:
            cause = self._connection_error.cause if self._connection_error else "connection lost"
            self._connection_error = DeviceConnectionError(
                self.name, "receive", f"{cause.split('; reconnect')[0]}; reconnect failed: {exc.cause}"
            )
            self._stop.wait(self.reconnect_interval)
            return
        with self._bus_lock:
            if self._stop.is_set():
                _shutdown(bus)
                return
            self._bus = bus
        self._connection_error = None
        self._consecutive_garbage = 0
        self._count("reconnects")

    def _count(self, key: str, amount: int = 1) -> None:
        with self._stats_lock:
            self._stats[key] += amount


# ---------------------------------------------------------------------------------------- helpers
def _is_garbage(exc: BaseException) -> bool:
    """True when the error is undecodable data rather than a broken transport."""
    chain: BaseException | None = exc
    while chain is not None:
        if isinstance(chain, OSError):
            return False
        if isinstance(chain, ValueError):  # includes UnicodeDecodeError
            return True
        chain = chain.__cause__
    return False


def _probe_socketcand(device: str, operation: str, host: str, port: int, timeout: float) -> None:
    try:
        with socket.create_connection((host, port), timeout=timeout) as probe:
            greeting = probe.recv(256)
    except OSError as exc:
        raise DeviceConnectionError(device, operation, f"socketcand at {host}:{port} not reachable: {exc}") from exc
    if greeting != b"< hi >":
        raise DeviceConnectionError(device, operation, f"socketcand at {host}:{port} greeted with {greeting[:40]!r}, "
                                    "expected b'< hi >'")


def _open_with_watchdog(device: str, operation: str, kwargs: Mapping[str, Any], timeout: float) -> can.BusABC:
    """``can.Bus(**kwargs)`` in a helper thread, so a daemon that stops answering mid-handshake
    cannot hang the caller. An abandoned attempt shuts its bus down if it ever completes."""
    result: dict[str, Any] = {}
    abandoned = threading.Event()

    def attempt() -> None:
        try:
            bus = can.Bus(**kwargs)
        except Exception as exc:
            # Keep only the text: the traceback holds the half-built bus and with it an open socket
            # or serial port, which would otherwise stay open until the garbage collector runs.
            result["error"] = f"{type(exc).__name__}: {exc}"
            return
        if abandoned.is_set():
            _shutdown(bus)
        else:
            result["bus"] = bus

    worker = threading.Thread(target=attempt, name=f"{device} CAN open", daemon=True)
    worker.start()
    worker.join(timeout)
    if worker.is_alive():
        abandoned.set()
        raise DeviceTimeout(device, operation, f"opening the {kwargs.get('interface')} bus took more than {timeout} s")
    if "error" in result:
        raise DeviceConnectionError(device, operation, result["error"])
    return result["bus"]


def _transport_alive(bus: can.BusABC) -> bool:
    """False when socketcand's TCP connection has reached EOF.

    python-can's socketcand client treats EOF as "no message" and never raises, so peek at its
    socket (a python-can 4.6 internal; without it we can only notice the silence)."""
    sock = getattr(bus, "_SocketCanDaemonBus__socket", None)
    if sock is None:
        return True
    try:
        return sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) != b""
    except BlockingIOError:
        return True
    except OSError:
        return False


def _shutdown(bus: can.BusABC | None) -> None:
    if bus is None:
        return
    try:
        bus.shutdown()
    except Exception:
        pass
    port = getattr(bus, "serialPortOrig", None)  # slcan: shutdown() skips closing if writing "C" failed
    if port is not None:
        try:
            port.close()
        except Exception:
            pass
