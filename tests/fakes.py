"""In-process fake cell for the procedure-layer tests: devices, operator, and a fake measurement core.

The fake world holds a true OPR pose; the robot moves it (with seeded repeatability noise), the
table turns it, the interferometer reads it, and ``FakeScience.measure`` returns it with a known
smooth systematic error plus noise, so the engine's results can be checked against truth.
Also runnable: ``python -m tests.fakes RUNS_DIR STATION PROCEDURE [--move-delay S] [--resume RUN]``
runs a procedure on the fakes in a child process (the kill -9 test).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import sys
import threading
import time
from pathlib import Path

import numpy as np
import yaml

from drivers import DeviceConnectionError, DeviceFault
from drivers.camera import Frame, GrabFailed
from drivers.interferometer import DatumLost, EnvironmentReading, FeedGap, HeadOptics
from drivers.robot import MotionEnvelope, ProtectiveStop, RobotIdentity, RobotState
from drivers.rotary_table import TableState
from instrument import COMPONENTS
from procedures.station import (
    CalibrationResult,
    MeasurementFailed,
    PoseMeasurement,
    euler_to_matrix,
    matrix_to_euler,
    tcp_in_m,
    ur_to_matrix,
)

REFERENCE_TCP = [0.45, -0.10, 0.27, np.pi, 0.0, 0.0]
TOOL_IN_OPR = [0.0, 0.0, 0.07, 0.0, 0.0, 0.0]


def station_dict(truth_log: str | None = None, **overrides) -> dict:
    """A valid station file for the fake cell. Its device entries name real adapters with loopback
    settings (the station must validate), but tests hand ``StationRuntime`` the fakes instead."""
    data = {
        "name": "fake cell",
        "devices": {
            "robot": {"adapter": "ur_rtde", "host": "127.0.0.1"},
            "cameras": {s: {"adapter": "pylon", "serial": f"fake-{s}"} for s in "xyz"},
            "rotary_table": {"adapter": "modbus_tcp", "host": "127.0.0.1", "port": 5020},
            "interferometer": {"adapter": "socketcand", "host": "127.0.0.1", "port": 29536, "channel": "can0"},
        },
        "geometry": {"screens": {s: {"origin": [0, 0, 0], "u": [1, 0, 0], "v": [0, 1, 0]} for s in "xyz"}},
        "frames": {"reference_tcp_pose": REFERENCE_TCP, "tcp_offset": [0, 0, 0.08, 0, 0, 0],
                   "tool_in_opr": TOOL_IN_OPR},
        "envelope": {"box_min": [0.2, -0.4, 0.1], "box_max": [0.7, 0.2, 0.5], "reference_rotvec": [np.pi, 0, 0],
                     "max_tilt": 0.5, "max_speed": 0.5, "max_acceleration": 2.0},
        "calibration": {"record": None},
        "operator": "none",
    }
    if truth_log:
        data["simulation"] = {"truth_log": truth_log}
    data.update(overrides)
    return data


def write_station(path: Path, **kwargs) -> Path:
    path.write_text(yaml.safe_dump(station_dict(**kwargs), sort_keys=False), encoding="utf-8")
    return path


def record_id_of(text: str) -> str:
    """A content hash as the fake calibration record's id."""
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()[:16]


def systematic_error(component: int, value: float) -> float:
    """The fake instrument's smooth error: ±50 µm on positions, ±10″ on angles."""
    if component < 3:
        return 50e-6 * np.sin(value / 0.02 + component)
    return np.radians(10 / 3600) * np.sin(value / 0.005 + component)


class FakeCell:
    """The shared truth and the devices around it."""

    def __init__(self, seed: int = 0, *, truth_log: str | Path | None = None, robot_sigma: float = 5e-6,
                 angle_sigma: float = 2e-5, move_delay: float = 0.0) -> None:
        self.rng = np.random.default_rng(seed)
        self.robot_sigma, self.angle_sigma, self.move_delay = robot_sigma, angle_sigma, move_delay
        self.lock = threading.Lock()
        self.opr_in_m = np.zeros(6)
        self.mount = "robot"
        self.aligned = None
        self.snapshots: dict[int, np.ndarray] = {}
        self.frame_ids = itertools.count(1)
        self.truth_path = Path(truth_log) if truth_log else None
        self.protective_stop_on_moves: set[int] = set()
        self.moves = 0
        self.fail_grabs = 0
        self.old_exposures = 0  # frame triples whose frames were exposed before the last motion ended
        self.old_after_moves: dict[int, int] = {}  # move number (1-based) → how many triples after it are that old
        self.fail_measures = 0
        # Frame triples that show the pose from before the last move (a camera that missed the new pose):
        # move number (1-based) → how many triples after it are stale.
        self.stale_after_moves: dict[int, int] = {}
        self.stale_grabs = 0
        self.previous_opr = np.zeros(6)
        self.lose_datum_on_reads: set[int] = set()  # interferometer.average calls (1-based) that lose the datum
        self.reads = 0
        # The air along the beam (K, Pa, fraction) and the material sensor; environment() calls (1-based) that
        # find no fresh reading, or a faulty sensor.
        self.air = {"air_temperature_k": 301.15, "pressure_pa": 92_000.0, "relative_humidity": 0.3}
        self.material_k = 301.35
        self.environment_gaps: set[int] = set()
        self.environment_faults: set[int] = set()
        self.environment_reads = 0
        self.log: list[str] = []
        # Motion in time (the kinds that measure while the robot moves): each move's controller times and
        # its path in M, with a known ring-down after the done signal (``true_at``).
        self.motions: list[FakeMotion] = []
        self.ring_amplitude_per_speed = 80e-6  # m of residual vibration per m/s of the move
        self.ring_frequency, self.ring_damping = 12.0, 0.2  # Hz, ζ
        self.max_move_duration = 0.15  # s of wall time a fake move takes at most
        self.stream_drops: set[int] = set()  # trigger numbers whose frames never arrive
        self.timed_moves = False  # True: every move takes time and rings down (the dynamic kinds' tests)
        self.robot = FakeRobot(self)
        self.cameras = {s: FakeCamera(self, s) for s in "xyz"}
        self.table = FakeTable(self)
        self.interferometer = FakeInterferometer(self)
        self.operator = FakeOperator(self)

    def devices(self) -> dict:
        return {"robot": self.robot, "rotary_table": self.table, "interferometer": self.interferometer,
                "camera_stream": FakeCameraStreams(self), **{f"camera:{s}": c for s, c in self.cameras.items()}}

    def true_at(self, times) -> np.ndarray:
        """(n, 6) the true OPR pose in M at controller times (``time.monotonic``)."""
        times = np.atleast_1d(np.asarray(times, dtype=float))
        with self.lock:
            motions = list(self.motions)
            rest = self.opr_in_m.copy()
        out = np.tile(rest, (len(times), 1))
        for i, t in enumerate(times):
            started = [m for m in motions if m.t_start <= t]
            if started:
                out[i] = started[-1].at(t, self)
            elif motions:
                out[i] = motions[0].waypoints[0]
        return out

    def set_truth(self, pose6: np.ndarray) -> None:
        with self.lock:
            self.previous_opr = self.opr_in_m.copy()
            self.opr_in_m = np.asarray(pose6, dtype=float)
        if self.truth_path:
            tool = matrix_to_euler(euler_to_matrix(self.opr_in_m) @ ur_to_matrix(TOOL_IN_OPR))
            entry = {"event": "pose", "time": time.time(), "mount": self.mount,
                     "opr_in_m": {"t": self.opr_in_m[:3].tolist(), "euler": self.opr_in_m[3:].tolist()},
                     "tool_in_m": {"t": tool[:3].tolist(), "euler": tool[3:].tolist()}}
            with open(self.truth_path, "a", encoding="utf-8") as handle:
                handle.write(json.dumps(entry) + "\n")


class FakeMotion:
    """One fake move: through ``waypoints`` (n, 6) in M at constant speed from ``t_start`` to ``t_done``,
    then a damped ring-down along the last segment's direction (amplitude ∝ speed)."""

    def __init__(self, t_start: float, t_done: float, waypoints: np.ndarray, speed: float) -> None:
        self.t_start, self.t_done, self.waypoints, self.speed = t_start, t_done, np.asarray(waypoints), speed
        lengths = np.linalg.norm(np.diff(self.waypoints[:, :3], axis=0), axis=1)
        self.cumulative = np.concatenate([[0.0], np.cumsum(lengths)])

    def at(self, t: float, cell: FakeCell) -> np.ndarray:
        end = self.waypoints[-1].copy()
        total = self.cumulative[-1]
        if t < self.t_done and total > 0:
            s = total * (t - self.t_start) / (self.t_done - self.t_start)
            k = min(int(np.searchsorted(self.cumulative, s, side="right")) - 1, len(self.waypoints) - 2)
            u = (s - self.cumulative[k]) / max(self.cumulative[k + 1] - self.cumulative[k], 1e-12)
            return self.waypoints[k] + u * (self.waypoints[k + 1] - self.waypoints[k])
        if total <= 0:
            return end
        direction = self.waypoints[-1, :3] - self.waypoints[-2, :3]
        direction = direction / max(np.linalg.norm(direction), 1e-12)
        omega = 2 * np.pi * cell.ring_frequency
        zeta = cell.ring_damping
        tau = t - self.t_done
        amplitude = cell.ring_amplitude_per_speed * self.speed
        end[:3] += direction * amplitude * np.exp(-zeta * omega * tau) * np.sin(omega * np.sqrt(1 - zeta**2) * tau)
        return end


class FakeRobot:
    name = "robot"

    def __init__(self, cell: FakeCell) -> None:
        self.cell = cell
        self.pose = np.array(REFERENCE_TCP, dtype=float)
        self.protective_stop = False
        self.stops = 0
        self.connected = False
        self.unreachable = False  # a controller that refuses connections (open() raises)
        self.envelope = MotionEnvelope.from_dict(station_dict()["envelope"])
        self.tcp = np.zeros(6)
        self.payload = (0.0, np.zeros(3))

    def identity(self) -> RobotIdentity:
        return RobotIdentity(manufacturer="Universal Robots", model="UR5", serial_number="20235500123",
                             controller_version="5.15.0.0")

    def set_payload(self, mass_kg: float, cog_m) -> None:
        cog = np.asarray(cog_m, dtype=float)
        if not (np.isfinite(mass_kg) and mass_kg >= 0) or cog.shape != (3,) or not np.all(np.isfinite(cog)):
            raise ValueError(f"robot: payload must be a finite mass >= 0 kg and 3 finite numbers (m), "
                             f"got {mass_kg!r}, {cog_m!r}")
        self.payload = (float(mass_kg), cog.copy())

    def set_tcp(self, offset) -> None:
        self.tcp = np.asarray(offset, dtype=float).copy()

    def tcp_offset(self) -> np.ndarray:
        return self.tcp.copy()

    def open(self) -> None:
        if self.unreachable:
            raise DeviceConnectionError("robot", "connect", "not reachable: [Errno 111] Connection refused")
        self.connected = True

    def close(self) -> None:
        self.connected = False

    def tcp_pose(self) -> np.ndarray:
        return self.pose.copy()

    def move_linear(self, pose, speed=0.25, acceleration=1.2, *, asynchronous=False, timeout=None) -> None:
        if self.cell.timed_moves:
            self._timed_move([pose], speed)
            return
        self.envelope.check_pose(pose)
        if self.protective_stop:
            raise ProtectiveStop("robot", "moveL", "robot is in protective stop")
        self.cell.moves += 1
        self.cell.stale_grabs = self.cell.stale_after_moves.get(self.cell.moves, 0)
        self.cell.old_exposures = self.cell.old_after_moves.get(self.cell.moves, 0)
        if self.cell.moves in self.cell.protective_stop_on_moves:
            self.protective_stop = True
            raise ProtectiveStop("robot", "moveL", "protective stop during the move (simulated collision)")
        if self.cell.move_delay:
            time.sleep(self.cell.move_delay)
        self.pose = np.asarray(pose, dtype=float)
        c = self.cell
        true = matrix_to_euler(tcp_in_m(REFERENCE_TCP, self.pose))
        true[:3] += c.rng.normal(0, c.robot_sigma, 3)
        true[3:] += c.rng.normal(0, c.angle_sigma, 3)
        if c.mount == "robot":
            c.set_truth(true)

    def stop(self, deceleration: float = 2.0) -> None:
        self.stops += 1

    # -- motion in time (controller clock: time.monotonic)
    def _timed_move(self, targets, speed: float) -> None:
        targets = np.atleast_2d(np.asarray(targets, dtype=float))
        for pose in targets:
            self.envelope.check_pose(pose)
        if self.protective_stop:
            raise ProtectiveStop("robot", "move", "robot is in protective stop")
        c = self.cell
        c.moves += 1
        with c.lock:
            start = c.opr_in_m.copy()
        waypoints = [start] + [matrix_to_euler(tcp_in_m(REFERENCE_TCP, p)) for p in targets]
        length = float(np.sum(np.linalg.norm(np.diff(np.array(waypoints)[:, :3], axis=0), axis=1)))
        duration = min(c.max_move_duration, length / max(float(speed), 1e-6))
        waypoints[-1][:3] += c.rng.normal(0, c.robot_sigma, 3)
        t_start = time.monotonic()
        motion = FakeMotion(t_start, t_start + duration, np.array(waypoints), float(speed))
        with c.lock:
            c.motions.append(motion)
        time.sleep(duration)
        self.pose = targets[-1].copy()
        self.done_time = motion.t_done
        if c.mount == "robot":
            c.set_truth(np.array(waypoints[-1]))

    def move_path(self, poses, speed=0.25, acceleration=1.2, blend_radius=0.0, *, asynchronous=False,
                  timeout=None) -> None:
        self._timed_move(poses, float(np.max(speed)))

    def move_circular(self, via, to, speed=0.25, acceleration=1.2, *, blend_radius=0.0, timeout=None) -> None:
        vias, tos = np.atleast_2d(via), np.atleast_2d(to)
        self._timed_move(np.array([p for pair in zip(vias, tos) for p in pair]), speed)

    def last_move_done_time(self) -> float | None:
        return getattr(self, "done_time", None)

    def controller_time(self) -> float:
        return time.monotonic()

    def is_steady(self) -> bool:
        return True

    def wait_until_steady(self, timeout: float = 10.0) -> None:
        pass

    def state(self) -> RobotState:
        return RobotState(connected=self.connected, protective_stop=self.protective_stop, emergency_stop=False,
                          program_running=True, steady=True)

    def clear_protective_stop(self) -> None:
        self.protective_stop = False


class FakeCamera:
    def __init__(self, cell: FakeCell, screen: str) -> None:
        self.cell, self.screen, self.name = cell, screen, f"camera {screen}"
        self.opened = False

    def open(self) -> None:
        self.opened = True

    def close(self) -> None:
        self.opened = False

    def grab(self, timeout: float = 2.0) -> Frame:
        if self.cell.fail_grabs > 0:
            self.cell.fail_grabs -= 1
            raise GrabFailed(self.name, "grab", "incomplete buffer (fake)")
        frame_id = next(self.cell.frame_ids)
        with self.cell.lock:
            stale = self.cell.stale_grabs > 0
            if stale and self.screen == "z":  # the last camera of a triple
                self.cell.stale_grabs -= 1
            self.cell.snapshots[frame_id] = (self.cell.previous_opr if stale else self.cell.opr_in_m).copy()
        image = np.full((8, 8), frame_id % 256, dtype=np.uint8)
        now = time.time()
        with self.cell.lock:  # a frame left in the camera's buffer from before the motion: exposed a second ago
            old = self.cell.old_exposures > 0
            if old and self.screen == "z":
                self.cell.old_exposures -= 1
        return Frame(image=image, timestamp=now, frame_id=frame_id, camera=self.screen, saturation=255,
                     exposure_start=now - 1.0 if old else now, evidence="exposure")


class FakeFrameStream:
    """A fake ``drivers.camera.FrameStream``: triggers at ``rate_hz`` from start to ``stop()``; each
    'image' carries its exposure's middle on the controller clock (the fake tracker reads the truth there)."""

    def __init__(self, cell: FakeCell, rate_hz: float, exposure_s: float) -> None:
        self.cell, self.rate_hz, self.exposure = cell, float(rate_hz), float(exposure_s)
        self.t0 = time.monotonic()
        self.pulses: np.ndarray | None = None
        self.closed = False
        self.offsets = {"x": 0.1, "y": -0.2, "z": 0.3}  # each camera's clock offset from the controller's, s

    def stop(self) -> None:
        if self.pulses is None:
            count = int((time.monotonic() - self.t0) * self.rate_hz) + 1
            self.pulses = self.t0 + np.arange(count) / self.rate_hz

    def sync_times(self):
        return self.pulses

    def __iter__(self):
        from types import SimpleNamespace

        assert self.pulses is not None
        for k, t in enumerate(self.pulses):
            if k in self.cell.stream_drops:
                yield SimpleNamespace(index=k, frames={}, timestamps={}, missing=dict.fromkeys("xyz", "fake drop"))
                continue
            middle = t + 0.5 * self.exposure
            frames = {s: np.array([middle]) for s in "xyz"}
            yield SimpleNamespace(index=k, frames=frames, timestamps={s: middle + o for s, o in self.offsets.items()},
                                  missing={})

    def close(self) -> None:
        self.closed = True


class FakeCameraStreams:
    """The station's ``camera_stream`` role on the fake cell."""

    def __init__(self, cell: FakeCell) -> None:
        self.cell = cell
        self.started: list[FakeFrameStream] = []

    def start_stream(self, rate_hz: float, *, exposure_s: float = 1e-3, timeout: float = 5.0, roi=None):
        stream = FakeFrameStream(self.cell, rate_hz, exposure_s)
        self.started.append(stream)
        return stream


class FakeTracker:
    """The fake core's stream: each trigger's pose is the truth at its exposure's middle, with the fake
    instrument's systematic error and noise, then ``compensate``."""

    def __init__(self, science: FakeScience, compensate) -> None:
        self.science, self.compensate = science, compensate
        self.rows: list[tuple] = []

    def add(self, index, timestamps, images):
        if set(images) != set("xyz"):
            return None
        t = float(images["x"][0])
        true = self.science.cell.true_at([t])[0]
        raw = np.array([true[i] + systematic_error(i, true[i]) for i in range(6)])
        raw[:3] += self.science.rng.normal(0, self.science.noise, 3)
        raw[3:] += self.science.rng.normal(0, self.science.angle_noise, 3)
        pose = raw if self.compensate is None else self.compensate(raw)
        self.rows.append((index, float(np.mean(list(timestamps.values()))), pose, raw))
        return None

    def stream(self):
        from types import SimpleNamespace

        n = len(self.rows)
        return SimpleNamespace(index=np.array([r[0] for r in self.rows], dtype=int),
                               time=np.array([r[1] for r in self.rows]),
                               pose=np.array([r[2] for r in self.rows]).reshape(n, 6),
                               raw=np.array([r[3] for r in self.rows]).reshape(n, 6),
                               residual_rms=np.full(n, 1e-7), timestamp_spread=np.zeros(n),
                               tracked=np.full(n, 3), drops=())


class FakeTable:
    name = "rotary_table"

    def __init__(self, cell: FakeCell) -> None:
        self.cell = cell
        self.angle = 0.0
        self.homed = False
        self.stops = 0

    def open(self) -> None:
        pass


    def close(self) -> None:
        pass

    def home(self, timeout: float = 30.0) -> None:
        self.homed, self.angle = True, 0.0

    def move_absolute(self, angle: float, speed: float | None = None) -> None:
        self.angle = float(angle)
        if self.cell.mount.startswith("table:"):
            k = "xyz".index(self.cell.mount[-1])
            pose = np.zeros(6)
            pose[3 + k] = self.angle
            self.cell.set_truth(pose)

    def wait_in_position(self, timeout: float = 30.0) -> float:
        return self.angle

    def position(self) -> float:
        return self.angle + self.cell.rng.normal(0, np.radians(0.1 / 3600))

    def stop(self) -> None:
        self.stops += 1

    def state(self) -> TableState:
        return TableState(in_position=True, moving=False, homed=self.homed, fault=None, position=self.angle)


class FakeInterferometer:
    """Reads the true displacement as a head with the default nominal air would in the cell's air:
    scaled by n(air)/n(nominal) (the real head's behaviour), so only a compensated reading is true."""

    name = "interferometer"

    def __init__(self, cell: FakeCell) -> None:
        self.cell = cell
        self.datum = 0.0
        self.optics = HeadOptics()

    def _index_ratio(self) -> float:
        from instrument.environment import AirConditions, wavelength_compensation_factor

        o, air = self.optics, self.cell.air
        nominal = AirConditions(o.nominal_air_temperature, o.nominal_pressure, o.nominal_relative_humidity,
                                o.nominal_co2)
        actual = AirConditions(air["air_temperature_k"], air["pressure_pa"], air["relative_humidity"], o.air_co2)
        return 1.0 / wavelength_compensation_factor(actual, nominal, o.vacuum_wavelength)

    def environment(self, max_age: float | None = None, *, strict: bool = True) -> EnvironmentReading:
        c = self.cell
        c.environment_reads += 1
        if c.environment_reads in c.environment_gaps:
            raise FeedGap(self.name, "environment", "no environmental reading received yet (fake)")
        if c.environment_reads in c.environment_faults and strict:
            raise DeviceFault(self.name, "environment", "sensor fault: air_temperature (fake)")
        now = time.time()
        return EnvironmentReading(timestamp=now, received=now, counter=c.environment_reads % 16,
                                  air_temperature_k=c.air["air_temperature_k"], pressure_pa=c.air["pressure_pa"],
                                  relative_humidity=c.air["relative_humidity"],
                                  material_temperatures_k=(c.material_k, float("nan"), float("nan")),
                                  material_fitted=(True, False, False), faults=())

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def _axis_value(self) -> float:
        return float(self.cell.opr_in_m["xyz".index(self.cell.aligned or "x")])

    def zero(self) -> None:
        self.datum = self._axis_value()
        self.has_datum = True

    has_datum = False  # a fresh head has none, like the real one

    def average(self, duration: float, timeout: float | None = None) -> float:
        self.cell.reads += 1
        if self.cell.reads in self.cell.lose_datum_on_reads:
            self.has_datum, self.datum = False, float("nan")  # a beam break loses the count
            raise DatumLost(self.name, "average", "beam not OK at sample 12 (fake beam break)")
        if not self.has_datum:
            raise DatumLost(self.name, "average", "no datum set since power-on or the last beam break")
        return (self._axis_value() - self.datum) * self._index_ratio() + self.cell.rng.normal(0, 0.1e-6)


class FakeOperator:
    def __init__(self, cell: FakeCell) -> None:
        self.cell = cell

    def mount_opr(self, where: str) -> None:
        self.cell.log.append(f"mount {where}")
        self.cell.mount = where
        if where == "robot":
            self.cell.robot.move_linear(self.cell.robot.pose)  # the truth follows the robot again
        else:
            self.cell.table.move_absolute(self.cell.table.angle)

    def align_interferometer(self, axis: str) -> None:
        self.cell.log.append(f"align {axis}")
        self.cell.aligned = axis


class FakeCompensator:
    def __init__(self, record: dict) -> None:
        self.record = record
        self.record_id = record["record_id"]
        self.directions_seen: list = []

    def correct(self, pose, direction=None):
        self.directions_seen.append(direction)
        pose = np.array(pose, dtype=float)
        for name, model in self.record["components"].items():
            i = COMPONENTS.index(name)
            pose[i] -= np.polyval(model["poly"], pose[i])
        return pose, []

    def info(self) -> dict:
        """No held-out evaluation: a run with only fake records has no uncertainty budget."""
        components = list(self.record["components"])
        return {"id": self.record_id, "path": None, "components": components,
                "methods": dict.fromkeys(components, "polynomial (fake)"),
                "validity": {c: m["range"] for c, m in self.record["components"].items()},
                "approach_directions": {c: [] for c in components}, "bidirectional": False, "date": "",
                "run_id": "", "references": [], "temperature_c": None, "evaluation": {}}


class FakeScience:
    """The measurement core's role, on the fake world (spec formulas where the core would compute)."""

    def __init__(self, cell: FakeCell, *, noise: float = 0.3e-6, angle_noise: float = 1e-7) -> None:
        self.cell, self.noise, self.angle_noise = cell, noise, angle_noise
        self.rng = np.random.default_rng(1234)

    def configure(self, station) -> None:
        self.station = station

    def measure(self, frames) -> PoseMeasurement:
        if self.cell.fail_measures > 0:
            self.cell.fail_measures -= 1
            raise MeasurementFailed("screen y: no cross found (fake)")
        true = self.cell.snapshots[frames["x"].frame_id]
        pose = np.array([true[i] + systematic_error(i, true[i]) for i in range(6)])
        pose[:3] += self.rng.normal(0, self.noise, 3)
        pose[3:] += self.rng.normal(0, self.angle_noise, 3)
        crosses = {s: {"center_px": [100.0, 100.0], "residual_rms_px": [0.05, 0.05]} for s in frames}
        return PoseMeasurement(pose=pose, residual_rms=1e-7, crosses=crosses)

    def pose_tracker(self, *, compensate=None) -> FakeTracker:
        return FakeTracker(self, compensate)

    def visibility_problems(self, opr_in_m):
        return [] if np.all(np.abs(opr_in_m[:3]) < 0.1) else ["cross off screen (fake)"]

    def fit_rigid_transform(self, source, target):
        cs, ct = source.mean(axis=0), target.mean(axis=0)
        u, _, vt = np.linalg.svd((source - cs).T @ (target - ct))
        d = np.sign(np.linalg.det(vt.T @ u.T))
        rotation = vt.T @ np.diag([1, 1, d]) @ u.T
        translation = ct - rotation @ cs
        rms = float(np.sqrt(np.mean(np.sum((source @ rotation.T + translation - target) ** 2, axis=1))))
        return rotation, translation, rms

    def iso_statistics(self, poses, commanded):
        poses = np.asarray(poses)
        bary = poses.mean(axis=0)
        l = np.linalg.norm(poses[:, :3] - bary[:3], axis=1)
        s = poses.std(axis=0, ddof=1)
        return {"n": len(poses), "rp_l": float(l.mean() + 3 * l.std(ddof=1)), "rp_a": 3 * s[3], "rp_b": 3 * s[4],
                "rp_c": 3 * s[5], "ap_p": float(np.linalg.norm(bary[:3] - commanded[:3])),
                "ap_a": bary[3] - commanded[3], "ap_b": bary[4] - commanded[4], "ap_c": bary[5] - commanded[5],
                "rp_l_ci": [float(l.mean() + 2.5 * l.std(ddof=1)), float(l.mean() + 3.6 * l.std(ddof=1))]}

    def fit_calibration(self, kind, data, provenance):
        components, curves = {}, {}
        for name, entries in data.items():
            measured = np.array([e["measured"] for e in entries])
            reference = np.array([e["reference"] for e in entries])
            error = measured - reference
            poly = np.polyfit(measured, error, 7)
            components[name] = {"poly": poly.tolist(), "range": [float(measured.min()), float(measured.max())]}
            curves[name] = {"measured": measured.tolist(), "reference": reference.tolist(),
                            "error_before": error.tolist(),
                            "error_after": (error - np.polyval(poly, measured)).tolist(),
                            "group": [e["group"] for e in entries]}
        body = {"kind": kind, "components": components}
        text = json.dumps(body, sort_keys=True)
        body["record_id"] = record_id_of(text)
        return CalibrationResult(record_json=json.dumps(body), record_id=body["record_id"], curves=curves,
                                 summary={"model": "polynomial (fake)"})

    def load_compensator(self, path):
        return FakeCompensator(json.loads(Path(path).read_text()))


def main(argv: list[str]) -> int:
    """Child-process entry for the kill -9 test."""
    import argparse

    from procedures.engine import open_engine

    parser = argparse.ArgumentParser()
    parser.add_argument("runs_dir")
    parser.add_argument("station")
    parser.add_argument("procedure")
    parser.add_argument("--move-delay", type=float, default=0.0)
    parser.add_argument("--resume", default=None)
    parser.add_argument("--timed", action="store_true", help="moves take time and ring down (the dynamic kinds)")
    args = parser.parse_args(argv)
    cell = FakeCell(seed=3, move_delay=args.move_delay)
    cell.timed_moves = args.timed
    with open_engine(args.runs_dir, procedure=args.procedure, station=args.station, run_id=args.resume,
                     science=FakeScience(cell), devices=cell.devices(), operator=cell.operator) as engine:
        print(engine.run_id, flush=True)
        state = engine.execute()
    print(state, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))


RECEIVED_EVENTS: list[dict] = []


def record_event(event: dict) -> None:
    """A hook target (``tests.fakes:record_event``)."""
    RECEIVED_EVENTS.append(event)


def failing_hook(event: dict) -> None:
    raise RuntimeError("the cell PLC is offline")


def slow_hook(event: dict) -> None:
    time.sleep(3.0)


def hanging_hook(event: dict) -> None:
    time.sleep(30.0)  # abandoned at its deadline; a daemon thread, gone with the process
