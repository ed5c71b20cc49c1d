"""The IRC5 controller behind the twin's RWS and EGM: panel, RAPID execution, the motion program
module, I/O signals, RAPID data, event log, RAMDISK files and faults, on the shared arm core.

What RAPID runs
---------------
Task ``T_ROB1`` holds ``motion_program_exec`` (abb_motion_program_exec's RAPID module); starting
it (cycle ``once``) runs ``motion_program_main``: read ``RAMDISK:motion_program.bin`` (``_program``),
``SetSysData`` its tool and work object and ``GripLoad`` its load, ask the ``logger`` task to open
``log-<timestamp>.bin`` (when ``motion_program_log_motion`` is 1), execute the commands, wait
for zero speed, close the log, write "Motion Program Complete" and stop. Every step writes the
module's own event log entries (``ErrWrite`` → code 80003 info, 80002 warning, 80001 error).

Motion commands become motions of the shared controller core (``sim_devices.arm``), so the arm
has the UR twin's servos, structural modes, repeatability and truth records; ``_planner`` turns
them into checked motions (paths with zones, joint moves, speeds; RAPID errors 50050/50063 before
anything moves). ``WaitTime`` waits at zero speed; ``CirPathMode``, ``SyncMoveOn/Off`` are accepted
and ignored; EGM guided motion (``EGMRunJoint`` …) is a RAPID error (not modelled).

Faults
------
``guardstop`` (FaultKind.PROTECTIVE_STOP), ``emergencystop`` (EMERGENCY_STOP) and ``motors_off``
stop the arm at the stop deceleration, put the panel in that state and stop RAPID (the program
pointer stays); a RAPID execution error (PROGRAM_STOPPED; code/title as parameters) stops RAPID
with the error and the module's "Motion Program Failed" warning. Armed faults fire during the next
move at path fraction ``at`` (default 0.5). ``clear_faults`` is the operator's reset: safety
circuits closed and motors on; ``release_safety`` leaves the controller in ``motoroff``.
"""

from __future__ import annotations

import datetime
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sim_devices._transforms import invert, matrix_to_pose6
from sim_devices.abb import _program as mp
from sim_devices.abb._config import ABBTwinConfig
from sim_devices.abb._kinematics import IRB2600, confdata, pose_from_abb, pose_to_abb
from sim_devices.abb._planner import Planner, RapidError, is_stop_point
from sim_devices.abb._rapid_data import RapidValueError, format_value, parse_value, tooldata_value
from sim_devices.arm import ArmController, IKFailed, Motion
from sim_devices.faults import FaultKind, FaultPlan

CTRL_STATES = ("init", "motoroff", "motoron", "guardstop", "emergencystop", "emergencystopreset", "sysfail")
LOCAL_FAULTS = ("motors_off",)  # the ABB twin's own fault names (beside sim_devices.faults.FaultKind)
ERRWRITE_CODES = {1: 80003, 2: 80002, 3: 80001}  # ErrWrite \I, \W and plain, by message type
# The controller's own event messages (elog domain 1, operational) for panel state changes.
STATE_EVENTS = {"motoroff": (10010, "Motors OFF state"), "motoron": (10011, "Motors ON state"),
                "guardstop": (10012, "Safety guard stop state"), "emergencystop": (10013, "Emergency stop state")}
# RWS error codes (the HRESULT-style numbers RWS puts in _embedded.status.code).
RWS_NOT_FOUND, RWS_REJECTED, RWS_BAD_VALUE = -1073442812, -1073445865, -1073442816
SIGNALS: dict[str, tuple[str, float]] = {  # name → (type, default) of EIO.cfg's signals
    "motion_program_executing": ("DO", 0), "motion_program_preempt": ("AO", 0),
    "motion_program_preempt_cmd_num": ("AO", -1), "motion_program_preempt_current": ("AO", 0),
    "motion_program_current_cmd_num": ("AO", -1), "motion_program_queued_cmd_num": ("AO", -1),
    "motion_program_seqno": ("AO", -1), "motion_program_log_motion": ("DO", 1), "motion_program_error": ("DO", 0),
    "motion_program_seqno_command": ("AO", 0), "motion_program_seqno_complete": ("AO", 0),
    "motion_program_driver_abort": ("DO", 0), "motion_program_seqno_started": ("AO", 0),
    "motion_program_stop_egm": ("DO", 0),
}
DEFAULT_TOOL = "[TRUE,[[0,0,0],[1,0,0,0]],[0.001,[0,0,0.001],[1,0,0,0],0,0,0]]"
DEFAULT_WOBJ = '[FALSE,TRUE,"",[[0,0,0],[1,0,0,0]],[[0,0,0],[1,0,0,0]]]'
DEFAULT_LOAD = "[0.001,[0,0,0.001],[1,0,0,0],0,0,0]"


class RwsError(Exception):
    """An RWS request the controller refuses: HTTP ``status`` and RWS ``code``."""

    def __init__(self, status: int, code: int, message: str) -> None:
        super().__init__(message)
        self.status, self.code, self.message = status, code, message


class _Stopped(Exception):
    """RAPID execution was stopped (a stop request, a safety stop, motors off)."""


@dataclass
class ElogEntry:
    seqnum: int
    msgtype: int
    code: int
    title: str
    desc: str
    args: list[str]
    tstamp: str
    conseqs: str = ""
    causes: str = ""
    actions: str = ""


class IRC5Arm(ArmController):
    """The shared controller core with the IRB 2600 arm; faults go to the IRC5's handler."""

    def __init__(self, world, config: ABBTwinConfig, faults: FaultPlan, on_fault: Callable[..., None]) -> None:
        super().__init__(world, config, faults, kinematics=IRB2600, stream_label="abb")
        self.on_fault = on_fault
        self.local_faults: list[tuple[str, dict[str, Any]]] = []  # armed ``motors_off`` faults
        self.fired_local: list[tuple[str, dict[str, Any]]] = []

    def trigger(self, kind: FaultKind | str, at_time: float | None = None) -> None:
        self.on_fault(kind, at_time)

    def _mid_move_faults(self, run, t: float) -> bool:  # the core's hook, extended by the local faults
        if super()._mid_move_faults(run, t):
            return True
        local = self.local_faults
        if not local or run.motion.stopped:
            return False
        name, params = local[0]
        if run.motion.fraction(t) < float(params.get("at", 0.5)):
            return False
        local.pop(0)
        self.fired_local.append((name, params))
        self.on_fault(name, run.motion.time_at_fraction(float(params.get("at", 0.5))))
        return True


@dataclass
class _Execution:
    state: str = "stopped"  # ctrlexecstate
    cycle: str = "once"
    pp_at_main: bool = True
    commands: list[mp.Command] = field(default_factory=list)
    next_index: int = 0  # where a start without resetpp goes on
    program: mp.MotionProgram | None = None


class IRC5:
    """The controller model (see the module docstring). Thread-safe; ``listeners`` hear every
    change a subscription can carry as ``(resource, value)``."""

    def __init__(self, world, config: ABBTwinConfig, faults: FaultPlan) -> None:
        self.config = config
        self.world = world
        self.faults = faults
        self.lock = threading.RLock()
        self.arm = IRC5Arm(world, config, faults, self._fault)
        self.planner = Planner(self.arm.kin, config)
        self.ctrlstate = "motoron"
        self.opmode = config.opmode
        self.speedratio = 100.0
        self.execution = _Execution()
        self.signals = {name: value for name, (_, value) in SIGNALS.items()}
        self.symbols: dict[str, str] = {
            "T_ROB1/motion_program_tool": DEFAULT_TOOL, "T_ROB1/motion_program_wobj": DEFAULT_WOBJ,
            "T_ROB1/motion_program_gripload": DEFAULT_LOAD, "T_ROB1/tool0": DEFAULT_TOOL, "T_ROB1/wobj0": DEFAULT_WOBJ,
            "T_ROB1/Module1/opr_counter": "0", "T_ROB1/Module1/opr_label": '""',
        }
        self.files: dict[str, bytes] = {}
        self.elog: list[ElogEntry] = []
        self._seqnum = 0
        self.listeners: list[Callable[[str, str], None]] = []
        self._runner: threading.Thread | None = None
        self._stop_request = threading.Event()
        self._log: dict[str, Any] | None = None  # the logger task's open joint log
        self.current_cmd_num = -1
        self._pending_error: RapidError | None = None
        self.programs_run = 0
        self.stop_history: list[str] = []
        self._elog_info(10011, "Motors ON state", "The system is in the Motors ON state.", domain_event=True)
        self._elog_info(10017, "Automatic mode confirmed", "The system has been set to automatic mode.",
                        domain_event=True)
        self.arm.add_cycle_listener(self._log_cycle)

    # ----------------------------------------------------------------------------- lifecycle
    def start(self) -> None:
        self.arm.start()

    def stop(self) -> None:
        self._stop_request.set()
        self.arm.stop()
        runner = self._runner
        if runner is not None and runner.is_alive():
            runner.join(2.0)

    @property
    def controller_time(self) -> float:
        return self.arm.cycle * self.arm.period

    # ----------------------------------------------------------------------------- events
    def _notify(self, resource: str, value: str) -> None:
        for listener in list(self.listeners):
            try:
                listener(resource, value)
            except Exception:  # a subscriber's problem is not the controller's
                pass

    def _elog(self, msgtype: int, code: int, title: str, desc: str, args: list[str]) -> ElogEntry:
        with self.lock:
            self._seqnum = self._seqnum % 65535 + 1  # uint16, as the controller counts
            stamp = datetime.datetime.now().strftime("%Y-%m-%d T %H:%M:%S")
            entry = ElogEntry(self._seqnum, msgtype, code, title, desc, args, stamp)
            self.elog.insert(0, entry)
            del self.elog[self.config.event_log_size:]
        self._notify("/rw/elog/0", str(entry.seqnum))
        return entry

    def _elog_info(self, code: int, title: str, desc: str, *, domain_event: bool = False) -> None:
        self._elog(1, code, title, desc, [] if domain_event else [title, desc])

    def errwrite(self, header: str, reason: str, *more: str, msgtype: int = 1) -> None:
        """RAPID ``ErrWrite``: the event's arguments are the header, the reason and \\RL2…\\RL4."""
        self._elog(msgtype, ERRWRITE_CODES[msgtype], header, " ".join((reason, *more)), [header, reason, *more])

    def set_signal(self, name: str, value: float) -> None:
        with self.lock:
            if name not in self.signals:
                raise RwsError(404, RWS_NOT_FOUND, f"signal {name} not found")
            changed = self.signals[name] != value
            self.signals[name] = value
        if changed:
            self._notify(f"signal:{name}", _signal_text(value))

    def signal(self, name: str) -> tuple[str, float]:
        with self.lock:
            if name not in self.signals:
                raise RwsError(404, RWS_NOT_FOUND, f"signal {name} not found")
            return SIGNALS[name][0], self.signals[name]

    def _set_ctrlstate(self, state: str) -> None:
        with self.lock:
            changed = state != self.ctrlstate
            self.ctrlstate = state
        if changed:
            if state in STATE_EVENTS:
                code, title = STATE_EVENTS[state]
                self._elog_info(code, title, f"The system is in the {title}.", domain_event=True)
            self._notify("/rw/panel/ctrlstate", state)

    def _set_execstate(self, state: str) -> None:
        with self.lock:
            changed = state != self.execution.state
            self.execution.state = state
        if changed:
            self.set_signal("motion_program_executing", 1 if state == "running" else 0)
            self._notify("/rw/rapid/execution;ctrlexecstate", state)

    # ----------------------------------------------------------------------------- RAPID data
    def symbol(self, path: str) -> str:
        key = self._symbol_key(path)
        with self.lock:
            return self.symbols[key]

    def set_symbol(self, path: str, value: str) -> None:
        key = self._symbol_key(path)
        try:
            parsed = parse_value(value)
        except RapidValueError as exc:
            raise RwsError(400, RWS_BAD_VALUE, str(exc)) from None
        with self.lock:
            old = parse_value(self.symbols[key])
            if _shape(parsed) != _shape(old):
                raise RwsError(400, RWS_BAD_VALUE, f"{value!r} does not fit the data type of {key}")
            self.symbols[key] = format_value(parsed)
        self._notify(f"symbol:{key}", self.symbols[key])

    def _symbol_key(self, path: str) -> str:
        """``T_ROB1/name`` or ``T_ROB1/Module/name`` as the RWS path gives it (a module is optional)."""
        parts = [p for p in path.split("/") if p]
        with self.lock:
            if "/".join(parts) in self.symbols:
                return "/".join(parts)
            for key in self.symbols:
                key_parts = key.split("/")
                if parts and key_parts[-1] == parts[-1] and (len(parts) == 1 or key_parts[0] == parts[0]):
                    return key
        raise RwsError(404, RWS_NOT_FOUND, f"symbol {path} not found")

    def tool_pose(self, name: str) -> np.ndarray:
        """The TCP frame (4×4, m, in tool0) of the tooldata ``name``."""
        value = parse_value(self.symbol(f"T_ROB1/{name}"))
        try:
            return pose_from_abb(value[1][0], value[1][1])
        except (IndexError, TypeError, ValueError):
            raise RwsError(400, RWS_BAD_VALUE, f"{name} is not a tooldata") from None

    # ----------------------------------------------------------------------------- files
    def _file_key(self, path: str) -> str:
        parts = [p for p in path.replace("\\", "/").split("/") if p]
        if parts and parts[0].upper() in ("$TEMP", "$RAMDISK", self.config.ramdisk_path.strip("/").upper()):
            parts[0] = "$TEMP"
        return "/".join(parts)

    def ramdisk_file(self, name: str) -> str:
        return self._file_key(f"{self.config.ramdisk_path}/{name}")

    def write_file(self, path: str, data: bytes) -> None:
        with self.lock:
            self.files[self._file_key(path)] = bytes(data)

    def read_file(self, path: str) -> bytes:
        with self.lock:
            key = self._file_key(path)
            if key not in self.files:
                raise RwsError(404, RWS_NOT_FOUND, f"file {path} not found")
            return self.files[key]

    def delete_file(self, path: str) -> None:
        with self.lock:
            if self.files.pop(self._file_key(path), None) is None:
                raise RwsError(404, RWS_NOT_FOUND, f"file {path} not found")

    def list_files(self, path: str) -> list[str]:
        prefix = self._file_key(path)
        with self.lock:
            return sorted(key[len(prefix) + 1:] for key in self.files if key.startswith(prefix + "/"))

    # ----------------------------------------------------------------------------- panel
    def set_controller_state(self, state: str) -> None:
        """RWS ``setctrlstate``: motors on (AUTO, no safety stop) or off."""
        with self.lock:
            current = self.ctrlstate
        if state == "motoroff":
            self._motors_off("motors off (requested)")
            return
        if state != "motoron":
            raise RwsError(400, RWS_BAD_VALUE, f"ctrl-state {state!r} cannot be set")
        if current in ("guardstop", "emergencystop", "emergencystopreset"):
            raise RwsError(400, RWS_REJECTED, f"Operation rejected by the controller: the controller is in {current}")
        if self.opmode != "AUTO":
            raise RwsError(400, RWS_REJECTED, "Operation rejected by the controller: motors on needs AUTO mode")
        self.arm.clear_safety()
        self._set_ctrlstate("motoron")

    def set_speedratio(self, ratio: float) -> None:
        if not 0 <= ratio <= 100:
            raise RwsError(400, RWS_BAD_VALUE, f"speed ratio {ratio} is not in 0 … 100")
        self.speedratio = float(ratio)

    # ----------------------------------------------------------------------------- execution
    def resetpp(self) -> None:
        with self.lock:
            if self.execution.state == "running":
                raise RwsError(400, RWS_REJECTED, "Operation rejected by the controller: RAPID is running")
            self.execution.pp_at_main = True
            self.execution.next_index = 0

    def start_execution(self, cycle: str) -> None:
        with self.lock:
            if self.execution.state == "running":
                raise RwsError(400, RWS_REJECTED, "Operation rejected by the controller: RAPID is already running")
            if self.ctrlstate != "motoron":
                raise RwsError(400, RWS_REJECTED, f"Operation rejected by the controller: {self.ctrlstate}")
            if self.opmode != "AUTO":
                raise RwsError(400, RWS_REJECTED, "Operation rejected by the controller: remote start needs AUTO")
            if cycle in ("once", "forever"):
                self.execution.cycle = cycle
            self._stop_request.clear()
            resume = not self.execution.pp_at_main
            self.execution.pp_at_main = False
            self._set_execstate("running")
            self._runner = threading.Thread(target=self._run_main, args=(resume,), name="abb-rapid-T_ROB1",
                                            daemon=True)
            self._runner.start()

    def stop_execution(self) -> None:
        """RWS ``stop``: RAPID stops, the arm decelerates on its path."""
        self._stop_request.set()
        self.arm.stop_motion(self.config.stop_deceleration)
        runner = self._runner
        if runner is not None and runner is not threading.current_thread():
            runner.join(5.0)
        self._set_execstate("stopped")

    def _run_main(self, resume: bool) -> None:
        """``motion_program_main`` on the RAPID task's thread."""
        try:
            if not resume:
                self._open_program()
            self._run_commands()
            self._wait_zero_speed()
            if self._log is not None:
                self._close_log()
            self.errwrite("Motion Program Complete", "Motion Program Complete")
            with self.lock:
                self.execution.pp_at_main = True
                self.execution.next_index = 0
                self.programs_run += 1
        except _Stopped as stop:
            self.stop_history.append(str(stop))
            error, self._pending_error = self._pending_error, None
            if error is not None:  # an injected execution error stopped it: the error event comes first
                self._rapid_error(error)
        except RapidError as error:
            self._rapid_error(error)
        except Exception as exc:  # the twin's own bug: shows as a system failure, never a hang
            self._rapid_error(RapidError(40000, "Execution error", f"{type(exc).__name__}: {exc}"))
        finally:
            self._set_execstate("stopped")

    def _rapid_error(self, error: RapidError) -> None:
        """An execution error: the error event, then the error_reporter task's warning."""
        self._elog(3, error.code, error.title, error.text, [error.title, error.text])
        self.errwrite("Motion Program Failed",
                      f"Motion Program Failed at command number {self.current_cmd_num}",
                      f"with error code {error.code}", f"error title '{error.title}'",
                      f"error string '{error.text}'", msgtype=2)
        if self._log is not None:  # the logger's error trap closes its file
            self._close_log()
        with self.lock:
            self.execution.pp_at_main = True
            self.execution.next_index = 0

    def _open_program(self) -> None:
        # motion_program_init: the command numbers start from -1 again
        for name in ("motion_program_current_cmd_num", "motion_program_queued_cmd_num"):
            self.set_signal(name, -1)
        self.current_cmd_num = -1
        self.errwrite("Motion Program Begin", "Motion Program Begin")
        try:
            data = self.read_file(self.ramdisk_file("motion_program.bin"))
        except RwsError:
            raise RapidError(40014, "File access error", "RAMDISK:motion_program.bin not found") from None
        try:
            program = mp.decode_program(data)
        except mp.ProgramError as exc:
            if exc.errname == "ERR_INVALID_MP_VERSION":
                self.errwrite("Invalid Motion Program", "Invalid motion program file version", msgtype=3)
            raise RapidError(40000 + {"ERR_FILESIZE": 1, "ERR_INVALID_MP_VERSION": 2, "ERR_INVALID_MP_FILE": 3,
                                      "ERR_INVALID_OPCODE": 4}.get(exc.errname, 9), exc.errname, str(exc)) from None
        self.errwrite("Motion Program Opened", f"Motion Program Opened with timestamp: {program.timestamp}")
        tool, load = program.tool, program.gripload
        with self.lock:
            self.execution.program = program
            self.execution.commands = program.commands
            self.execution.next_index = 0
            self.symbols["T_ROB1/motion_program_tool"] = format_value(tooldata_value(
                tool.robhold, tool.tframe.trans, tool.tframe.rot, tool.tload.mass, tool.tload.cog, tool.tload.aom,
                tool.tload.inertia))
            self.symbols["T_ROB1/motion_program_gripload"] = format_value(
                [load.mass, list(load.cog), list(load.aom), *load.inertia])
        self._notify("symbol:T_ROB1/motion_program_tool", self.symbols["T_ROB1/motion_program_tool"])
        self.set_signal("motion_program_seqno", program.seqno)
        # SetSysData of the tool; GripLoad: the structure carries the tool's load and the payload.
        self.arm.set_tcp(matrix_to_pose6(pose_from_abb(tool.tframe.trans, tool.tframe.rot)))
        mass = tool.tload.mass + load.mass
        cog = (np.asarray(tool.tload.cog) * tool.tload.mass + np.asarray(load.cog) * load.mass) / max(mass, 1e-12)
        if abs(mass - self.arm.payload_mass) > 1e-9 or not np.allclose(cog * 1e-3, self.arm.payload_cog, atol=1e-12):
            self.arm.set_payload(mass, cog * 1e-3)
        self.errwrite("Motion Program Start Program",
                      f"Motion Program Start Program timestamp: {program.timestamp}")
        if self._log is not None:
            self._close_log()
        if self.signals["motion_program_log_motion"] > 0:
            self._open_log(program.timestamp)

    # ----------------------------------------------------------------------------- the joint log
    def _open_log(self, timestamp: str) -> None:
        name = f"log-{timestamp}.bin"
        with self.lock:
            self._log = {"name": name, "data": bytearray(mp.log_header(timestamp)), "t0": self.controller_time}
        self.errwrite("Motion Program Log File Opened", f"Motion Program Log File Opened with filename: {name}")

    def _close_log(self) -> None:
        with self.lock:
            log, self._log = self._log, None
            if log is not None:
                self.files[self.ramdisk_file(log["name"])] = bytes(log["data"])
        if log is not None:
            self.errwrite("Motion Program Log File Closed", "Motion Program Log File Closed")

    def _log_cycle(self, state) -> None:
        """The logger task's 4 ms loop, on the controller cycle (one row per cycle while executing)."""
        log = self._log
        if log is None or self.execution.state != "running":
            return
        clock = state.cycle * self.arm.period - log["t0"]
        log["data"] += mp.log_row(clock, self.current_cmd_num, list(np.degrees(state.fields["actual_q"])))

    # ----------------------------------------------------------------------------- commands
    def _run_commands(self) -> None:
        while True:
            with self.lock:
                commands, index = self.execution.commands, self.execution.next_index
            if index >= len(commands):
                return
            group = [commands[index]]
            if commands[index].name in ("MoveL", "MoveC", "EGMMoveL", "EGMMoveC"):
                while not is_stop_point(group[-1]) and index + len(group) < len(commands) and \
                        commands[index + len(group)].name in ("MoveL", "MoveC", "EGMMoveL", "EGMMoveC"):
                    group.append(commands[index + len(group)])
            self._check_running()
            self._execute(group)
            with self.lock:
                self.execution.next_index = index + len(group)

    def _set_cmd(self, cmd_num: int) -> None:
        self.current_cmd_num = cmd_num
        self.set_signal("motion_program_current_cmd_num", cmd_num)

    def _execute(self, group: list[mp.Command]) -> None:
        first = group[0]
        self.set_signal("motion_program_queued_cmd_num", group[-1].cmd_num)
        if first.name == "WaitTime":
            self._wait_zero_speed()
            self._set_cmd(first.cmd_num)
            self._sleep(float(first.params["seconds"]))
        elif first.name in ("CirPathMode", "SyncMoveOn", "SyncMoveOff"):
            self._set_cmd(first.cmd_num)
        elif first.name in ("MoveAbsJ", "MoveJ"):
            self._move(self.planner.joint(first, *self._at_rest(), self._frames()), [first.cmd_num])
        elif first.name in ("MoveL", "MoveC", "EGMMoveL", "EGMMoveC"):
            self._move(self.planner.path(group, *self._at_rest(), self._frames()), [c.cmd_num for c in group])
        else:
            raise RapidError(41000, "Instruction not supported", f"{first.name}: EGM guided motion is not modelled "
                             "by the twin")

    def _at_rest(self) -> tuple[np.ndarray, np.ndarray]:
        """The joints and TCP offset the next motion starts from (RAPID waits for a fine point first)."""
        self._wait_zero_speed()
        with self.arm.lock:
            return self.arm.q.copy(), self.arm.tcp_offset.copy()

    def _frames(self) -> np.ndarray:
        """The running program's work object: user frame ∘ object frame (the base frame for wobj0)."""
        program = self.execution.program
        if program is None:
            return np.eye(4)
        w = program.wobj
        return pose_from_abb(w.uframe.trans, w.uframe.rot) @ pose_from_abb(w.oframe.trans, w.oframe.rot)

    def _move(self, factory: Callable[[float, np.ndarray, np.ndarray], Motion], cmd_nums: list[int]) -> None:
        """Run one planned motion (``factory`` is cheap: the checks ran before) and wait until it is done."""
        done = threading.Event()
        self._set_cmd(cmd_nums[0])
        try:
            self.arm.start_motion(factory, on_done=lambda _motion: done.set())
        except RuntimeError:  # refused: a safety stop came first
            raise _Stopped(f"motion refused in {self.ctrlstate}") from None
        except IKFailed:
            raise RapidError(50050, "Position outside reach", "The position (robtarget) is outside the robot's "
                             "working area") from None
        with self.arm.lock:
            run = self.arm.run
            if run is not None and len(cmd_nums) > 1:
                run.progress = lambda passed: self._set_cmd(cmd_nums[min(passed, len(cmd_nums) - 1)])
        while not done.wait(0.05):
            if self._stop_request.is_set() or self.arm._stop.is_set():
                self.arm.stop_motion(self.config.stop_deceleration)
                done.wait(5.0)
                raise _Stopped("RAPID stop requested")
        self._check_running()

    def _check_running(self) -> None:
        if self._stop_request.is_set():
            raise _Stopped("RAPID stop requested")
        with self.lock:
            state = self.ctrlstate
        if state != "motoron":
            raise _Stopped(f"the controller went to {state}")

    def _wait_zero_speed(self) -> None:
        deadline = time.monotonic() + 30.0
        while self.arm.moving and time.monotonic() < deadline:
            self._check_running()
            time.sleep(0.005)
        self._check_running()

    def _sleep(self, seconds: float) -> None:
        until = time.monotonic() + max(seconds, 0.0) / self.config.time_scale
        while time.monotonic() < until:
            self._check_running()
            time.sleep(min(0.01, max(until - time.monotonic(), 0.0)))

    # ----------------------------------------------------------------------------- faults
    def _fault(self, kind: Any, at_time: float | None = None) -> None:
        """Make a fault happen now (or, for a stop, at simulated time ``at_time``)."""
        name = kind.value if isinstance(kind, FaultKind) else str(kind)
        if name == FaultKind.PROTECTIVE_STOP.value:
            self.arm.protective_stop("guard stop (injected)", at_time)
            self._set_ctrlstate("guardstop")
            self._stop_request.set()
        elif name == FaultKind.EMERGENCY_STOP.value:
            self.arm.emergency_stop("emergency stop (injected)", at_time)
            self._set_ctrlstate("emergencystop")
            self._stop_request.set()
        elif name == "motors_off":
            self._motors_off("motors off (injected)", at_time)
        elif name == FaultKind.PROGRAM_STOPPED.value:
            armed = [params for k, params in self.faults.fired() if k is FaultKind.PROGRAM_STOPPED]
            params = armed[-1] if armed else {}
            self._inject_rapid_error(int(params.get("code", 40223)), str(params.get("title", "Execution error")),
                                     str(params.get("text", "Execution error (injected)")), at_time)
        elif name == FaultKind.DISCONNECT.value:
            self.arm.log("connections dropped (injected)")
            threading.Thread(target=self.arm.on_disconnect, daemon=True).start()
        else:
            raise ValueError(f"fault {name!r} cannot be triggered on the IRC5 twin")

    def _motors_off(self, reason: str, at_time: float | None = None) -> None:
        run = self.arm.run
        if run is not None and run.phase == "moving":
            run.motion.stop(self.arm.t_sim if at_time is None else at_time, self.config.stop_deceleration)
        self.arm.log(reason)
        self._stop_request.set()
        self._set_ctrlstate("motoroff")

    def _inject_rapid_error(self, code: int, title: str, text: str, at_time: float | None) -> None:
        run = self.arm.run
        if run is not None and run.phase == "moving":
            run.motion.stop(self.arm.t_sim if at_time is None else at_time, self.config.stop_deceleration)
        with self.lock:
            running = self.execution.state == "running"
            if running:
                self._pending_error = RapidError(code, title, text)
        if running:
            self._stop_request.set()  # the task's thread writes the error before RAPID shows stopped
        else:
            self._elog(3, code, title, text, [title, text])

    def clear_faults(self) -> None:
        """The operator's reset: safety circuits closed, motors on, faults disarmed."""
        self.faults.clear()
        self.arm.local_faults.clear()
        self.arm.clear_safety()
        self._set_ctrlstate("motoron")

    def release_safety(self) -> None:
        """Guard or emergency stop reset: the controller waits in motors off."""
        self.arm.clear_safety()
        self._set_ctrlstate("motoroff")

    # ----------------------------------------------------------------------------- readback
    def jointtarget(self) -> np.ndarray:
        """Axis positions (degrees) of the encoders."""
        with self.arm.lock:
            return np.degrees(self.arm.q + self.arm.error)

    def robtarget(self, tool: str, wobj: str, coordinate: str) -> tuple[np.ndarray, np.ndarray, tuple]:
        """(mm, quaternion, confdata) of the TCP of ``tool`` from the encoders, in the base frame."""
        tool_pose = self.tool_pose(tool)
        with self.arm.lock:
            q = self.arm.q + self.arm.error
        tcp = self.arm.kin.forward(q) @ tool_pose
        if coordinate.lower() == "wobj":
            value = parse_value(self.symbol(f"T_ROB1/{wobj}"))
            frame = pose_from_abb(*value[3]) @ pose_from_abb(*value[4])
            tcp = invert(frame) @ tcp
        trans, quat = pose_to_abb(tcp)
        return trans, quat, confdata(q)

    def describe(self) -> dict[str, Any]:
        with self.lock:
            return {"ctrlstate": self.ctrlstate, "opmode": self.opmode, "execution": self.execution.state,
                    "pp_at_main": self.execution.pp_at_main, "current_cmd_num": self.current_cmd_num,
                    "programs_run": self.programs_run, "speedratio": self.speedratio,
                    "elog_seqnum": self._seqnum, "controller_time": self.controller_time,
                    **{f"arm_{k}": v for k, v in self.arm.describe().items()}}


def _signal_text(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else format(value, ".9g")


def _shape(value: Any) -> Any:
    return [_shape(v) for v in value] if isinstance(value, list) else type(value).__name__
