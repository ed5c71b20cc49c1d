"""The simulated cell: every twin in its own process around one shared world, and its control API.

``CellHost`` is the supervisor. It builds the seeded world and shares its state
(``World.share``: one small memory-mapped state file, ``sim_devices._world_channel``), then starts
one process per twin — the camera file twin (with the optical bench), the UR controller twin, the
rotary table twin (Modbus TCP/RTU, GCS serial) and the interferometer twin (socketcand, slcan) —
each attached to that world, writes a station YAML with every endpoint, serves a control channel
(the simulated operator: re-mount the OPR on the table, re-aim the interferometer; fault
injection; ground truth) and watches its twins: one that dies is reported by name (stderr, the
truth log, ``status()``, and every control call that needs it). No twin outlives the supervisor:
each stops when its control pipe to the supervisor closes or its parent changes
(``sim_devices._process``).

With a process per twin, the 500 Hz robot cycle, the 1 kHz interferometer clock and the camera
renderer no longer share one interpreter: none can starve another, and the renderer is out of the
robot's control path (the robot announces a move's end pose when it plans it, so the frames are
usually ready when the move ends; its "done" still waits until the cameras show the final pose).

``SimCell`` runs a ``CellHost`` in a child process (the ur_rtde client must never share a process
with its twin) and offers the same typed methods; it is what tests and ``instrument run --station
sim`` use; ``instrument sim`` runs a ``CellHost`` in the foreground.
"""

from __future__ import annotations

import os
import shutil
import socket
import sys
import tempfile
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from multiprocessing.connection import wait as wait_for_exits
from pathlib import Path
from typing import Any, Literal, Protocol

import numpy as np
import yaml

from sim_devices._config import checked_fields
from sim_devices._process import TWIN_NICE, TwinProcess, TwinProcessError
from sim_devices._transforms import invert, matrix_to_pose6
from sim_devices.camera import OpticalBench
from sim_devices.control import ControlClient, ControlServer, dispatch
from sim_devices.faults import FaultKind, fault_kind
from sim_devices.world import Axis, World, WorldConfig

UR_PORTS = (30004, 29999, 30003)

TwinName = Literal["cameras", "robot", "rotary_table", "interferometer"]
TWIN_NAMES: tuple[TwinName, ...] = ("cameras", "robot", "rotary_table", "interferometer")
FAULT_TWINS = ("robot", "rotary_table", "interferometer")


class Stoppable(Protocol):
    def request_stop(self) -> None: ...

    def stop(self) -> None: ...


LOOPBACK_BLOCK_ENV = "SIM_LOOPBACK_BLOCK"
"""Environment variable naming the 127.A.B block (``"127.0.7"``) in which twins take their addresses
(default ``127.0.0``): parallel test workers get disjoint blocks, so their cells never compete."""

STATIC_ROBOT = {"truth_rate": 0.0}
"""The ``robot`` section of a cell config whose runs measure at rest: the robot twin without its dense
truth (the true tool at 1 kHz of simulated time, with its structural ring-down, into each move's
trajectory record). Nothing such a run sees reads it (once a move is done the world holds the settled
pose), and sampling it is most of the robot twin's CPU while it moves and for up to 3 simulated seconds
after each move."""


def loopback_block() -> str:
    """The ``127.A.B`` block twins bind in (``SIM_LOOPBACK_BLOCK``, default ``127.0.0``)."""
    block = os.environ.get(LOOPBACK_BLOCK_ENV, "127.0.0")
    parts = block.split(".")
    if len(parts) != 3 or parts[0] != "127" or not all(p.isdigit() and int(p) <= 255 for p in parts):
        raise ValueError(f"{LOOPBACK_BLOCK_ENV} must be a 127.A.B loopback block, got {block!r}")
    return block


def free_loopback_host(first: int = 2, last: int = 254, exclude: tuple[str, ...] = (),
                       tcp_ports: tuple[int, ...] = UR_PORTS, udp_ports: tuple[int, ...] = ()) -> str:
    """A loopback address ``<block>.N`` (``first`` ≤ N ≤ ``last``, in ``loopback_block()``) on which the
    fixed ports a twin binds (the UR ports by default; ``udp_ports`` for a datagram protocol) are free
    right now."""
    block = loopback_block()
    wanted = [(port, socket.SOCK_STREAM) for port in tcp_ports] + [(port, socket.SOCK_DGRAM) for port in udp_ports]
    for n in range(first, last + 1):
        host = f"{block}.{n}"
        if host in exclude:
            continue
        sockets = []
        try:
            for port, kind in wanted:
                s = socket.socket(socket.AF_INET, kind)
                sockets.append(s)
                s.bind((host, port))
            return host
        except OSError:
            continue
        finally:
            for s in sockets:
                s.close()
    raise RuntimeError(f"no loopback address with ports {tcp_ports} (TCP) {udp_ports} (UDP) free in "
                       f"{block}.{first}-{last}")


@dataclass(frozen=True)
class CellConfig:
    """The sections of a cell configuration (``instrument sim --config``); each is a mapping that its
    own twin's settings check (unknown keys are refused there, unknown sections here)."""

    world: Mapping[str, Any] = field(default_factory=dict)
    optics: Mapping[str, Any] = field(default_factory=dict)
    cameras: Mapping[str, Any] = field(default_factory=dict)
    robot: Mapping[str, Any] = field(default_factory=dict)
    rotary_table: Mapping[str, Any] = field(default_factory=dict)
    interferometer: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> CellConfig:
        sections = checked_fields(cls, data, "cell config")
        for name, value in sections.items():
            if value is None:
                sections[name] = {}
            elif not isinstance(value, Mapping):
                raise ValueError(f"cell config: section {name} must be a mapping, got {type(value).__name__}")
        return cls(**sections)

    def check(self) -> None:
        """Build every twin's settings once, so a bad key is one ``ValueError`` before any process starts."""
        from sim_devices.camera import OpticsConfig, StreamConfig
        from sim_devices.interferometer import InterferometerTwinConfig
        from sim_devices.rotary_table import RotaryTableTwinConfig
        from sim_devices.ur import URTwinConfig

        WorldConfig.from_dict(self.world)
        OpticsConfig.from_dict(self.optics)
        StreamConfig.from_dict(_stream_section(self.cameras))
        URTwinConfig.from_dict(self.robot)
        RotaryTableTwinConfig.from_dict(self.rotary_table)
        InterferometerTwinConfig.from_dict(self.interferometer)


FILE_TWIN_KEYS = ("render_delay", "stamp_frames")  # the camera file twin's own keys of the cameras section


def _stream_section(cameras: Mapping[str, Any]) -> dict[str, Any]:
    """The ``cameras`` section without the file twin's own keys, which it checks: ``render_delay`` (s
    the file twin waits before it puts a settled pose's frames in place: a slow renderer on demand,
    for the race tests) and ``stamp_frames`` (embed a frame stamp in every frame; default true)."""
    delay = cameras.get("render_delay", 0.0)
    if not isinstance(delay, (int, float)) or delay < 0:
        raise ValueError(f"cameras config: render_delay must be a number of seconds ≥ 0, got {delay!r}")
    if not isinstance(cameras.get("stamp_frames", True), bool):
        raise ValueError(f"cameras config: stamp_frames must be true or false, got {cameras['stamp_frames']!r}")
    return {key: value for key, value in cameras.items() if key not in FILE_TWIN_KEYS}


def _stamps_frames(config: CellConfig) -> bool:
    return bool(config.cameras.get("stamp_frames", True))


class CellNotRunning(RuntimeError):
    """A control method of a cell that is not running (not started, or stopped), or of a twin that died."""


class TwinHandle:
    """The supervisor's handle on one twin process: its control API by name, its process and health."""

    def __init__(self, name: str, process: TwinProcess) -> None:
        self.name = name
        self.process = process
        self.died: int | None = None  # exit code, once the twin died while the cell ran
        self.realtime = False  # its threads run under SCHED_RR (the robot and interferometer, if allowed)

    @property
    def endpoints(self) -> dict[str, Any]:
        return self.process.endpoints

    @property
    def pid(self) -> int | None:
        return self.process.pid

    @property
    def alive(self) -> bool:
        return self.died is None and self.process.alive

    def control(self, command: str, /, **kwargs: Any) -> Any:
        """The twin's own control API (or the cell's ``cell.*`` wiring) in its process."""
        if not self.alive:
            code = self.died if self.died is not None else self.process.poll_exit()
            raise CellNotRunning(f"simulated cell: the {self.name} twin is not running (it died, exit code {code})")
        try:
            return self.process.call(command, **kwargs)
        except TwinProcessError as exc:
            if not self.process.alive:
                raise CellNotRunning(f"simulated cell: the {self.name} twin died during {command!r}") from None
            raise RuntimeError(str(exc)) from None

    def status(self) -> dict[str, Any]:
        alive = self.alive
        code = self.died
        if not alive and code is None:  # ended, and the monitor has not recorded it yet: read it here
            code = self.process.poll_exit(timeout=2.0)
        return {"pid": self.pid, "alive": alive, "exitcode": code, "realtime": self.realtime}

    def request_stop(self) -> None:
        self.process.request_stop()

    def stop(self) -> None:
        self.process.stop()


class CellHost:
    """The supervisor of the simulated cell (see module docstring).

    Parameters
    ----------
    directory : str
        Where the cell writes camera frames, the ground-truth log, the shared world and ``station.yaml``.
    seed : int
        Seed of every random stream in the cell.
    robot_host : str, optional
        Loopback address for the UR twin (fixed ports); a free one is picked when omitted.
    time_scale : float
        Simulated time runs this many times faster than wall time (robot and table motion).
    config : mapping, optional
        Per-twin settings (``CellConfig``): ``world``, ``optics``, ``robot``, ``rotary_table``,
        ``interferometer``. Checked when the cell starts (a bad setting is a ``ValueError``).
    session : int
        Which start of this cell this is for the run it serves (0 the first): the same physics (true
        geometry, mounts, biases: from ``seed``) with every noise drawn anew, as a real cell started
        again has (``WorldConfig.session``). The station file and the truth log record it.

    After ``start()``: ``world`` (the supervisor's view of the shared ``World``), ``bench`` (the
    ``OpticalBench``, as the camera process builds it) and one ``TwinHandle`` per twin process,
    ``cameras``, ``robot``, ``rotary_table``, ``interferometer`` (``CellNotRunning`` before and after).
    """

    def __init__(self, directory: str, seed: int = 0, robot_host: str | None = None, time_scale: float = 1.0,
                 config: Mapping[str, Any] | None = None, session: int = 0) -> None:
        self.directory = Path(directory)
        self.seed = int(seed)
        self.session = int(session)
        self.robot_host = robot_host
        self.time_scale = float(time_scale)
        self.config = dict(config or {})
        self._world: World | None = None
        self._bench: OpticalBench | None = None
        self._twins: dict[str, TwinHandle] = {}
        self._started: list[tuple[str, Stoppable]] = []  # in start order; stopped in reverse
        self._control: ControlServer | None = None
        self._stopping = threading.Event()
        self._monitor: threading.Thread | None = None
        self.endpoints: dict[str, Any] = {}
        # The control API by name (the JSON channel and TwinProcess): one explicit table.
        self._commands: dict[str, Callable[..., Any]] = {
            "ping": self.ping,
            "status": self.status,
            "mount_on_table": self.mount_on_table,
            "mount_on_robot": self.mount_on_robot,
            "align_interferometer": self.align_interferometer,
            "inject_fault": self.inject_fault,
            "clear_faults": self.clear_faults,
            "fired_faults": self.fired_faults,
            "truth": self.truth,
            "true_opr_in_m": self.true_opr_in_m,
            "describe": self.describe,
            "device": self.forward,
        }

    # ------------------------------------------------------------------------------ the twins
    @property
    def world(self) -> World:
        return self._running(self._world, "world")

    @property
    def bench(self) -> OpticalBench:
        return self._running(self._bench, "optical bench")

    @property
    def cameras(self) -> TwinHandle:
        return self.twin("cameras")

    @property
    def robot(self) -> TwinHandle:
        return self.twin("robot")

    @property
    def rotary_table(self) -> TwinHandle:
        return self.twin("rotary_table")

    @property
    def interferometer(self) -> TwinHandle:
        return self.twin("interferometer")

    @staticmethod
    def _running(part: Any, what: str) -> Any:
        if part is None:
            raise CellNotRunning(f"simulated cell: the {what} is not running (start the cell first)")
        return part

    def twin(self, name: str) -> TwinHandle:
        """One twin's handle by name (``cameras``, ``robot``, ``rotary_table``, ``interferometer``)."""
        if name not in TWIN_NAMES:
            raise ValueError(f"simulated cell: no twin {name!r}; expected one of {', '.join(TWIN_NAMES)}")
        return self._running(self._twins.get(name), f"{name} twin")

    # ------------------------------------------------------------------------------ lifecycle
    def start(self) -> dict[str, Any]:
        """Share the world, start one process per twin, the control channel and the station file;
        returns the endpoints.

        Raises
        ------
        ValueError
            A bad setting in the cell configuration (one line naming it). Nothing is started.
        RuntimeError
            A twin failed to start (its message). Nothing stays running.
        """
        config = CellConfig.from_dict(self.config)
        config.check()
        self.directory.mkdir(parents=True, exist_ok=True)
        truth_path = self.directory / "truth.jsonl"
        trajectories = self.directory / "trajectories"  # the robot's dense truth (sim_devices.trajectory)
        world_section = {**config.world, "seed": self.seed, "session": self.session}
        self._world = world = World(WorldConfig.from_dict(world_section), truth_path=truth_path)
        self._stopping.clear()
        try:
            world_dir = str(world.share(self.directory / "world"))
            self._bench = bench = OpticalBench(world, config.optics)
            host = self.robot_host or free_loopback_host()
            settings: dict[str, dict[str, Any]] = {
                "cameras": {"frames": str(self.directory / "frames"), "optics": dict(config.optics),
                            "stream": _stream_section(config.cameras), "trajectories": str(trajectories),
                            "render_delay": float(config.cameras.get("render_delay", 0.0)),
                            "stamp_frames": _stamps_frames(config)},
                "robot": {"host": host, "time_scale": self.time_scale, "seed": self.seed,
                          "trajectory_dir": str(trajectories), **config.robot},
                "rotary_table": {**config.rotary_table, "time_scale": self.time_scale},
                "interferometer": dict(config.interferometer),
            }
            common = {"world_dir": world_dir, "world": world_section, "truth_path": str(truth_path)}
            for name in TWIN_NAMES:  # launched together: their start-ups overlap
                self._launch(name, {**common, "kind": name, "settings": settings[name]})
            for name in TWIN_NAMES:
                self.endpoints[name] = self._wait_started(name, common, settings)
                self._twins[name].realtime = bool(self._twins[name].control("cell.realtime"))
            self._monitor = threading.Thread(target=self._watch_twins, name="cell-monitor", daemon=True)
            self._monitor.start()
            self._control = ControlServer(self.control)
            control_host, control_port = self._control.start()
            self.endpoints["control"] = {"host": control_host, "port": control_port}
            self.endpoints["truth_log"] = str(truth_path)
            self.endpoints["station"] = str(self.write_station())
            world.truth.record("cell", time=world.clock(), describe=world.describe(),
                               optics=bench.true_description(), endpoints=self.endpoints,
                               twins={name: handle.pid for name, handle in self._twins.items()})
        except TwinProcessError as exc:
            self.stop()
            raise RuntimeError(f"simulated cell: {exc}") from None
        except BaseException:
            self.stop()
            raise
        return self.endpoints

    def _launch(self, name: str, kwargs: dict[str, Any]) -> None:
        # The renderer is not real time (a settled pose waits for it, bounded by the acknowledgement
        # timeout): it keeps the host's priority, so it never crowds out the robot's 500 Hz cycle.
        process = TwinProcess("sim_devices._cell_twins:CellTwin", kwargs, start_timeout=60.0, call_timeout=30.0,
                              name=f"{name} twin", nice=0 if name == "cameras" else TWIN_NICE)
        handle = self._twins[name] = TwinHandle(name, process)
        self._started.append((name, handle))
        process.launch()

    def _wait_started(self, name: str, common: dict[str, Any], settings: dict[str, dict[str, Any]]) -> dict[str, Any]:
        """The twin's endpoints; the robot moves to another free loopback address if its ports were
        taken between the check and its bind (another cell starting at the same time)."""
        tried: list[str] = []
        while True:
            try:
                return self._twins[name].process.wait_started()
            except TwinProcessError as exc:
                if name != "robot" or self.robot_host or "cannot bind" not in str(exc) or len(tried) >= 5:
                    raise
                tried.append(settings["robot"]["host"])
                self._started = [(n, h) for n, h in self._started if h is not self._twins[name]]
                settings["robot"]["host"] = free_loopback_host(exclude=tuple(tried))
                self._launch(name, {**common, "kind": name, "settings": settings[name]})

    def stop(self) -> None:
        """Stop everything started, even when one part fails to stop; then report the failures."""
        self._stopping.set()
        problems = []
        if self._control is not None:
            control, self._control = self._control, None
            try:
                control.stop()
            except Exception as exc:
                problems.append(f"control channel: {type(exc).__name__}: {exc}")
        for _, twin in self._started:  # told all at once, they stop side by side
            try:
                twin.request_stop()
            except Exception:
                pass  # its stop() below tries again and reports what fails
        while self._started:
            name, twin = self._started.pop()
            try:
                twin.stop()
            except Exception as exc:
                problems.append(f"{name}: {type(exc).__name__}: {exc}")
        if self._monitor is not None:
            self._monitor.join(5.0)
            self._monitor = None
        self._twins = {}
        self._bench = None
        if self._world is not None:
            world, self._world = self._world, None
            world.close()
            shutil.rmtree(self.directory / "world", ignore_errors=True)  # the state file and wake-up FIFOs
        if problems:
            raise RuntimeError("simulated cell: stopping failed for " + "; ".join(problems))

    def _watch_twins(self) -> None:
        """Report a twin whose process ends while the cell runs (by name), and free its world slots."""
        while not self._stopping.is_set():
            handles = {h.process.sentinel: h for h in self._twins.values() if h.died is None and h.process.alive}
            sentinels = [s for s in handles if s is not None]
            if not sentinels:
                self._stopping.wait(0.5)
                continue
            for sentinel in wait_for_exits(sentinels, timeout=0.5):
                if self._stopping.is_set():
                    return
                handle = handles[sentinel]  # type: ignore[index]
                self._report_death(handle)

    def _report_death(self, handle: TwinHandle) -> None:
        pid = handle.pid
        code = handle.process.poll_exit(timeout=2.0)  # its pipe closes a moment before it can be reaped
        handle.died = -1 if code is None else code
        world = self._world
        if world is not None and world.channel is not None and pid is not None:
            world.channel.release_slots_of(pid)
            world.truth.record("twin_died", time=world.clock(), twin=handle.name, pid=pid, exitcode=handle.died)
        print(f"simulated cell: the {handle.name} twin (pid {pid}) died, exit code {handle.died}",
              file=sys.stderr, flush=True)

    # ------------------------------------------------------------------------------ control API
    def control(self, command: str, /, **args: Any) -> Any:
        """Run the control method named ``command`` with ``args`` (the JSON channel, ``TwinProcess``).

        Raises
        ------
        ValueError
            Unknown command (the known ones are named) or arguments that do not fit it.
        """
        return dispatch(self._commands, command, args, "simulated cell")

    def ping(self) -> str:
        return "pong"

    def status(self) -> dict[str, dict[str, Any]]:
        """Each twin's process: ``pid``, ``alive``, for one that died its ``exitcode``, and ``realtime``
        (its threads run under SCHED_RR: the robot and the interferometer, where the system allows it)."""
        if not self._twins:
            raise CellNotRunning("simulated cell: not running (start the cell first)")
        return {name: handle.status() for name, handle in self._twins.items()}

    def mount_on_table(self, axis: Axis) -> str:
        """The operator puts the OPR on the rotary table, its axis along M's ``axis``; returns the mount."""
        world = self.world
        world.mount_on_table(axis)
        self.rotary_table.control("cell.sync")  # the OPR now takes the table's angle at once
        return world.mount

    def mount_on_robot(self) -> str:
        """The operator puts the OPR back on the robot flange; returns the mount."""
        world = self.world
        world.mount_on_robot()
        return world.mount

    def align_interferometer(self, axis: Axis) -> dict[str, Any]:
        """The operator re-aims the interferometer along M's ``axis`` (its count is lost); returns its truth."""
        return dict(self.interferometer.control("align", axis=axis))

    def _fault_twin(self, device: str) -> TwinHandle:
        if device == "cameras":
            raise ValueError("simulated cell: the camera file twin takes no faults (the pylon emulator's own "
                             "ForceFailedBuffer is driven through the camera adapter)")
        if device not in FAULT_TWINS:
            raise ValueError(f"simulated cell: no twin {device!r} takes faults; expected robot, rotary_table or "
                             "interferometer")
        return self.twin(device)

    def inject_fault(self, device: TwinName, kind: FaultKind | str, count: int = 1, transport: str | None = None,
                     **params: Any) -> list[str]:
        """Arm a fault on one twin; returns the kinds armed on that fault plan now.

        Parameters
        ----------
        device : "robot", "rotary_table" or "interferometer"
        kind : FaultKind or str
            What happens (``sim_devices.faults.FaultKind``); which kinds a twin takes and their
            ``params`` are in its docs page.
        count : int
            How many times it fires (-1: until cleared).
        transport : str, optional
            Rotary table: the endpoint (``modbus_tcp``, the station's, by default; ``modbus_rtu``,
            ``gcs``). Interferometer: the transport a ``disconnect`` hits (default: all).
        **params
            The fault's parameters (``seconds``, ``code``, ``frames``, ``at`` ...).
        """
        twin = self._fault_twin(device)
        kind = fault_kind(kind)
        if device == "robot" and transport is not None:
            raise ValueError(f"simulated cell: the robot twin has one fault plan; got transport {transport!r}")
        if device == "interferometer" and transport is not None:
            params["transport"] = transport
            transport = None
        return list(twin.control("cell.arm", kind=kind.value, count=int(count), transport=transport, params=params))

    def clear_faults(self, device: TwinName, transport: str | None = None) -> list[str]:
        """Disarm every fault of one twin (the robot also leaves a safety stop); returns what is still armed."""
        return list(self._fault_twin(device).control("cell.clear", transport=transport))

    def fired_faults(self, device: TwinName, transport: str | None = None) -> list[tuple[str, dict[str, Any]]]:
        """Every fault that fired on one twin (endpoint) so far, oldest first: ``(kind, params)``."""
        return [(str(kind), dict(params))
                for kind, params in self._fault_twin(device).control("cell.fired", transport=transport)]

    def truth(self, event: str | None = None, last: int = 1000) -> list[dict[str, Any]]:
        """The last ``last`` entries of the ground-truth log (of one ``event`` kind, or all)."""
        if last <= 0:
            return []
        return self.world.truth.entries(event)[-int(last):]

    def true_opr_in_m(self) -> list[list[float]]:
        """The OPR's true pose in M now (4×4)."""
        return self.world.opr_in_m().tolist()

    def describe(self) -> dict[str, Any]:
        """The world's and the optics' true description (for reports and tests)."""
        return {"world": self.world.describe(), "optics": self.bench.true_description()}

    def forward(self, device: TwinName, command: str, **args: Any) -> Any:
        """Run ``command`` of one twin's own control API (``{"command": "device", "args": {"device": ...,
        "command": ..., ...}}`` on the channel)."""
        return self.twin(device).control(command, **args)

    # ------------------------------------------------------------------------------ station file
    def station(self) -> dict[str, Any]:
        world = self.world
        assert world is not None
        kin = world.config.kinematics
        reference_tcp = world.nominal_base_to_m  # TCP = nominal OPR: at the reference it sits at M
        tool_in_opr = invert(world.nominal_opr_mount) @ world.nominal_tool
        frames_dir = self.directory / "frames"
        robot = self.endpoints["robot"]
        table = self.endpoints["rotary_table"]
        ifm = self.endpoints["interferometer"]
        reference_position = reference_tcp[:3, 3]
        return {
            "name": f"simulated cell (seed {self.seed})",
            "devices": {
                "robot": {"adapter": "ur_rtde", "host": robot["host"]},
                "cameras": {
                    axis: {"adapter": "pylon", "serial": serial, "emulator_image": str(frames_dir / f"{axis}.bmp"),
                           **({"embedded_stamp": True} if _stamps_frames(CellConfig.from_dict(self.config)) else {})}
                    for axis, serial in zip("xyz", ("0815-0000", "0815-0001", "0815-0002"))
                },
                "rotary_table": {"adapter": "modbus_tcp", "host": "127.0.0.1", "port": table["modbus_tcp_port"],
                                 "unit": int((self.config.get("rotary_table") or {}).get("unit", 1))},
                "interferometer": {"adapter": "socketcand", "host": ifm["socketcand"]["host"],
                                   "port": ifm["socketcand"]["port"],
                                   "channel": ifm["socketcand"].get("channel", "can0")},
            },
            "geometry": self.bench.nominal_geometry(),
            "frames": {
                "reference_tcp_pose": matrix_to_pose6(reference_tcp).tolist(),
                "tcp_offset": list(map(float, kin.opr_mount_nominal)),
                "tool_in_opr": matrix_to_pose6(tool_in_opr).tolist(),
            },
            "envelope": {
                "box_min": (reference_position - 0.15).tolist(),
                "box_max": (reference_position + 0.15).tolist(),
                "reference_rotvec": matrix_to_pose6(reference_tcp)[3:].tolist(),
                "max_tilt": float(np.radians(10.0)),
                "max_speed": 1.0,
                "max_acceleration": 3.0,
            },
            "calibration": {"record": None},
            "simulation": {"control": dict(self.endpoints["control"]), "truth_log": self.endpoints["truth_log"],
                           "seed": self.seed, "session": self.session},
        }

    def write_station(self) -> Path:
        path = self.directory / "station.yaml"
        tmp = path.with_suffix(".yaml.tmp")
        tmp.write_text("# Written by the simulated cell; endpoints are valid while it runs.\n"
                       + yaml.safe_dump(self.station(), sort_keys=False))
        tmp.replace(path)
        return path


class SimCell:
    """The simulated cell in a child process, as a context manager, with the typed control methods
    of ``CellHost`` (each runs in the child).

    >>> with SimCell(seed=1) as cell:          # doctest: +SKIP
    ...     station = cell.station_path         # a station YAML for the drivers
    ...     cell.mount_on_table("x")
    ...     cell.inject_fault("rotary_table", "exception", code=4)
    """

    def __init__(self, seed: int = 0, directory: str | Path | None = None, robot_host: str | None = None,
                 time_scale: float = 1.0, config: Mapping[str, Any] | None = None, start_timeout: float = 60.0,
                 session: int = 0):
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        if directory is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="simcell-")
            directory = self._tmp.name
        self.directory = Path(directory)
        self._process = TwinProcess(
            "sim_devices.cell:CellHost",
            {"directory": str(self.directory), "seed": seed, "robot_host": robot_host, "time_scale": time_scale,
             "config": dict(config or {}), "session": session},
            start_timeout=start_timeout, call_timeout=30.0,
        )
        self.endpoints: dict[str, Any] = {}

    def start(self) -> SimCell:
        self.endpoints = self._process.start()
        return self

    def stop(self) -> None:
        self._process.stop()
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    @property
    def supervisor_pid(self) -> int | None:
        """The process id of the cell's supervisor (its twins are that process's children)."""
        return self._process.pid

    @property
    def station_path(self) -> Path:
        return Path(self.endpoints["station"])

    @property
    def truth_path(self) -> Path:
        return Path(self.endpoints["truth_log"])

    def control(self, command: str, /, **args: Any) -> Any:
        """``CellHost.control`` in the child: any control method by name."""
        return self._process.call(command, **args)

    def client(self) -> ControlClient:
        """A client of the cell's JSON control channel (the same commands, over loopback TCP)."""
        return ControlClient(self.endpoints["control"]["host"], self.endpoints["control"]["port"])

    # ------------------------------------------------------------------------------ typed control
    # The same methods and signatures as CellHost's (a test compares them).
    def ping(self) -> str:
        return str(self.control("ping"))

    def status(self) -> dict[str, dict[str, Any]]:
        return dict(self.control("status"))

    def mount_on_table(self, axis: Axis) -> str:
        return str(self.control("mount_on_table", axis=axis))

    def mount_on_robot(self) -> str:
        return str(self.control("mount_on_robot"))

    def align_interferometer(self, axis: Axis) -> dict[str, Any]:
        return dict(self.control("align_interferometer", axis=axis))

    def inject_fault(self, device: TwinName, kind: FaultKind | str, count: int = 1, transport: str | None = None,
                     **params: Any) -> list[str]:
        return list(self.control("inject_fault", device=device, kind=str(kind), count=count, transport=transport,
                                 **params))

    def clear_faults(self, device: TwinName, transport: str | None = None) -> list[str]:
        return list(self.control("clear_faults", device=device, transport=transport))

    def fired_faults(self, device: TwinName, transport: str | None = None) -> list[tuple[str, dict[str, Any]]]:
        return list(self.control("fired_faults", device=device, transport=transport))

    def truth(self, event: str | None = None, last: int = 1000) -> list[dict[str, Any]]:
        return list(self.control("truth", event=event, last=last))

    def true_opr_in_m(self) -> list[list[float]]:
        return list(self.control("true_opr_in_m"))

    def describe(self) -> dict[str, Any]:
        return dict(self.control("describe"))

    def forward(self, device: TwinName, command: str, **args: Any) -> Any:
        return self.control("device", device=device, command=command, **args)

    def __enter__(self) -> SimCell:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
