"""The whole simulated cell in one process: every twin around one world model.

``CellHost`` builds the world, the optical bench and camera file twin, the UR controller twin, the
rotary table twins (Modbus TCP/RTU, GCS serial) and the interferometer twins (socketcand, slcan),
starts them, writes a station YAML with every endpoint, and serves a control channel (the
simulated operator: re-mount the OPR on the table, re-aim the interferometer; fault injection;
ground truth). ``SimCell`` runs a ``CellHost`` in a child process (the ur_rtde client must never
share a process with its twin) and is what tests and ``instrument run --station sim`` use;
``instrument sim`` runs one in the foreground.
"""

from __future__ import annotations

import socket
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sim_devices._process import TwinProcess
from sim_devices._transforms import invert, matrix_to_pose6
from sim_devices.control import ControlClient, ControlServer
from sim_devices.world import World, WorldConfig

UR_PORTS = (30004, 29999, 30003)


def free_loopback_host(first: int = 2, last: int = 254, exclude: tuple[str, ...] = ()) -> str:
    """A 127.0.0.N address on which the fixed UR ports are free right now."""
    for n in range(first, last + 1):
        host = f"127.0.0.{n}"
        if host in exclude:
            continue
        sockets = []
        try:
            for port in UR_PORTS:
                s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                sockets.append(s)
                s.bind((host, port))
            return host
        except OSError:
            continue
        finally:
            for s in sockets:
                s.close()
    raise RuntimeError("no loopback address with the UR ports free in 127.0.0.2-254")


def _scaled_clock(scale: float):
    """A monotonic clock that runs ``scale`` times faster than wall time."""
    origin = time.monotonic()
    return lambda: origin + (time.monotonic() - origin) * scale


class CellHost:
    """All twins of the simulated cell around one ``World`` (see module docstring).

    Parameters
    ----------
    directory : str
        Where the cell writes camera frames, the ground-truth log and ``station.yaml``.
    seed : int
        Seed of every random stream in the cell.
    robot_host : str, optional
        Loopback address for the UR twin (fixed ports); a free one is picked when omitted.
    time_scale : float
        Simulated time runs this many times faster than wall time (robot and table motion).
    config : mapping, optional
        Per-twin settings: ``world``, ``optics``, ``robot``, ``rotary_table``, ``interferometer``.
    """

    def __init__(self, directory: str, seed: int = 0, robot_host: str | None = None, time_scale: float = 1.0,
                 config: Mapping[str, Any] | None = None) -> None:
        self.directory = Path(directory)
        self.seed = int(seed)
        self.robot_host = robot_host
        self.time_scale = float(time_scale)
        self.config = dict(config or {})
        self.world: World | None = None
        self.bench: Any = None
        self._twins: dict[str, Any] = {}
        self._control: ControlServer | None = None
        self.endpoints: dict[str, Any] = {}

    # ------------------------------------------------------------------------------ lifecycle
    def start(self) -> dict[str, Any]:
        from sim_devices.camera_twin import CameraFileTwin
        from sim_devices.interferometer import InterferometerTwin
        from sim_devices.optics import OpticalBench
        from sim_devices.rotary_table import RotaryTableTwin
        from sim_devices.ur import URControllerTwin

        self.directory.mkdir(parents=True, exist_ok=True)
        world_cfg = WorldConfig.from_dict({**dict(self.config.get("world") or {}), "seed": self.seed})
        self.world = world = World(world_cfg, truth_path=self.directory / "truth.jsonl")
        try:
            self.bench = OpticalBench(world, self.config.get("optics"))
            self._add("cameras", CameraFileTwin(world, self.bench, self.directory / "frames"))
            host = self.robot_host or free_loopback_host()
            self._add("robot", URControllerTwin(world, host, {"time_scale": self.time_scale, "seed": self.seed,
                                                             **dict(self.config.get("robot") or {})}))
            self._add("rotary_table", RotaryTableTwin(world, self.config.get("rotary_table"),
                                                      clock=_scaled_clock(self.time_scale)))
            self._add("interferometer", InterferometerTwin(world, self.config.get("interferometer")))
            self._control = ControlServer(self.control)
            control_host, control_port = self._control.start()
            self.endpoints["control"] = {"host": control_host, "port": control_port}
            self.endpoints["truth_log"] = str(self.directory / "truth.jsonl")
            self.endpoints["station"] = str(self.write_station())
            world.truth.record("cell", time=world.clock(), describe=world.describe(),
                               optics=self.bench.true_description(), endpoints=self.endpoints)
        except BaseException:
            self.stop()
            raise
        return self.endpoints

    def _add(self, name: str, twin: Any) -> None:
        self._twins[name] = twin
        self.endpoints[name] = twin.start()

    def stop(self) -> None:
        """Stop everything started, even when one part fails to stop; then report the failures."""
        problems = []
        if self._control is not None:
            control, self._control = self._control, None
            try:
                control.stop()
            except Exception as exc:
                problems.append(f"control channel: {type(exc).__name__}: {exc}")
        for name in reversed(list(self._twins)):
            try:
                self._twins.pop(name).stop()
            except Exception as exc:
                problems.append(f"{name}: {type(exc).__name__}: {exc}")
        if self.world is not None:
            self.world.truth.close()
        if problems:
            raise RuntimeError("simulated cell: stopping failed for " + "; ".join(problems))

    # ------------------------------------------------------------------------------ control API
    def control(self, command: str, **args: Any) -> Any:
        world = self.world
        assert world is not None
        if command == "ping":
            return "pong"
        if command == "mount_on_table":
            world.mount_on_table(args["axis"])
            self._twins["rotary_table"].sync()  # the OPR now takes the table's angle at once
            return world.mount
        if command == "mount_on_robot":
            world.mount_on_robot()
            return world.mount
        if command == "align_interferometer":
            return self._twins["interferometer"].control("align", axis=args["axis"])
        if command == "truth":
            return world.truth.entries(args.get("event"))[-int(args.get("last", 1000)):]
        if command == "true_opr_in_m":
            return world.opr_in_m().tolist()
        if command == "describe":
            return {"world": world.describe(), "optics": self.bench.true_description()}
        if command == "device":  # forward to one twin's own control API
            twin = self._twins[args.pop("device")]
            return twin.control(args.pop("command"), **args)
        raise ValueError(f"unknown cell command {command!r}")

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
                    axis: {"adapter": "pylon", "serial": serial, "emulator_image": str(frames_dir / f"{axis}.bmp")}
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
                           "seed": self.seed},
        }

    def write_station(self) -> Path:
        path = self.directory / "station.yaml"
        tmp = path.with_suffix(".yaml.tmp")
        tmp.write_text("# Written by the simulated cell; endpoints are valid while it runs.\n"
                       + yaml.safe_dump(self.station(), sort_keys=False))
        tmp.replace(path)
        return path


class SimCell:
    """The simulated cell in a child process, as a context manager.

    >>> with SimCell(seed=1) as cell:          # doctest: +SKIP
    ...     station = cell.station_path         # a station YAML for the drivers
    ...     cell.control("mount_on_table", axis="x")
    """

    def __init__(self, seed: int = 0, directory: str | Path | None = None, robot_host: str | None = None,
                 time_scale: float = 1.0, config: Mapping[str, Any] | None = None, start_timeout: float = 60.0):
        self._tmp = None
        if directory is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="simcell-")
            directory = self._tmp.name
        self.directory = Path(directory)
        self._process = TwinProcess(
            "sim_devices.cell:CellHost",
            {"directory": str(self.directory), "seed": seed, "robot_host": robot_host, "time_scale": time_scale,
             "config": dict(config or {})},
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
    def station_path(self) -> Path:
        return Path(self.endpoints["station"])

    @property
    def truth_path(self) -> Path:
        return Path(self.endpoints["truth_log"])

    def control(self, command: str, **args: Any) -> Any:
        return self._process.call(command, **args)

    def client(self) -> ControlClient:
        return ControlClient(self.endpoints["control"]["host"], self.endpoints["control"]["port"])

    def __enter__(self) -> SimCell:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
