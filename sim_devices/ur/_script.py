"""Emulation of ur_rtde's ``rtde_control.script`` main loop over the RTDE registers.

The real script (uploaded on port 30003) loops every controller cycle: it reads the command id from
``input_int_register_0`` (+ offset), runs it, and answers through ``output_int_register_0``: 1 =
ready for a command, 2 = done with it; the client then writes 0 and the script says ready again.
"Real-time" commands are answered with ready, not done. Asynchronous moves run in a move "thread"
and report through the async progress register ``output_int_register_2`` (operation id in bits
24–30, write count in 16–23, running flag in bit 15, progress in 0–14). Command 255 ends the script.

This module reproduces that loop event-driven (it wakes on every input-register write and on motion
ends), with the same register layout and the same order of writes.
"""

from __future__ import annotations

import re
import threading
import time

import numpy as np

from sim_devices._transforms import matrix_to_pose6, pose6_to_matrix
from sim_devices.arm import Motion as ArmMotion
from sim_devices.faults import FaultKind
from sim_devices.ur import _kinematics as kin
from sim_devices.ur._controller import RUNTIME_STOPPED, URController
from sim_devices.ur._motion import Motion
from sim_devices.ur._urscript import ScriptError, function_body, path_moves, plan_path

REALTIME_COMMANDS = {6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71}
COMMAND_NAMES = {
    1: "moveJ", 2: "moveJ_IK", 3: "moveL", 4: "moveL_FK", 17: "setPayload", 29: "setTcp",
    30: "getInverseKinematics(args)",
    31: "triggerProtectiveStop", 33: "stopL", 34: "stopJ", 36: "isPoseWithinSafetyLimits",
    37: "isJointsWithinSafetyLimits", 39: "poseTrans", 40: "getTCPOffset", 43: "getForwardKinematics()",
    44: "getForwardKinematics(args)", 45: "movePath", 46: "getInverseKinematics()", 47: "isSteady",
    58: "getActualToolFlangePose", 60: "getInverseKinematicsHasSolution()",
    61: "getInverseKinematicsHasSolution(args)", 65: "setTargetPayload", 255: "stopScript",
}
JOINT_LIMIT = 2 * np.pi


def register_offset(text: str, kind: str) -> int:
    """The register offset ur_rtde injected for ``kind`` (``int`` or ``float``), 0 if none.

    The client puts the number AFTER the comment that ends the line, at the start of the next one
    (``global reg_offset_float = # float register offset⏎24    global reg_offset_int = …``), so
    the value is the first number after ``=`` once a comment up to the end of the line is skipped.
    """
    match = re.search(rf"global\s+reg_offset_{kind}\s*=[ \t]*(?:#[^\n]*\n)?\s*(\d+)", text)
    return int(match.group(1)) if match else 0


def recognise_control_script(text: str) -> tuple[int, int] | None:
    """Register offsets (int, float) if ``text`` is ur_rtde's control script, else None."""
    if "RTDE Control Script" not in text or "def rtde_control" not in text:
        return None
    return register_offset(text, "int"), register_offset(text, "float")


class ControlScript:
    """One run of the control script on the twin controller."""

    def __init__(self, controller: URController, int_offset: int = 0, float_offset: int = 0,
                 name: str = "rtde_control", program: str = "") -> None:
        self.c = controller
        self.int_offset = int_offset
        self.float_offset = float_offset
        self.name = name
        # ur_rtde injects a path (moveL(path), movePath) into exec_move_path() before uploading.
        self.path_lines = function_body(program, "exec_move_path") or []
        self.alive = True
        self._async_wr_count = 0
        self._async_op_id = 0
        self._async_motion: ArmMotion | None = None
        self._stop_motion_pending = False
        self._thread = threading.Thread(target=self._run, name=f"ur-script-{name}", daemon=True)

    # ----------------------------------------------------------------------------- registers
    def _in_int(self, i: int) -> int:
        return self.c.in_int[i + self.int_offset]

    def _in_double(self, i: int) -> float:
        return self.c.in_double[i + self.float_offset]

    def _in_vector(self, start: int) -> np.ndarray:
        return np.array([self._in_double(start + k) for k in range(6)])

    def _out_int(self, i: int, value: int) -> None:
        self.c.out_int[i + self.int_offset] = int(value)

    def _out_vector(self, start: int, values) -> None:
        for k, v in enumerate(values):
            self.c.out_double[start + k + self.float_offset] = float(v)

    def _write_async_progress(self, value: int) -> None:
        """Same arithmetic as ``write_async_progress_register`` in the real script."""
        with self.c.lock:
            self._async_wr_count = 0 if self._async_wr_count >= 127 else self._async_wr_count + 1
            if value == 0:
                self._async_op_id = 0 if self._async_op_id >= 127 else self._async_op_id + 1
            reg = self._async_wr_count * 65536 + self._async_op_id * 16777216
            if value >= 0:
                reg += min(value, 32767) + 32768
            self._out_int(2, reg)

    def _signal_ready(self) -> None:
        self._out_int(0, 1)

    def _signal_done(self) -> None:
        self._out_int(0, 2)

    # ----------------------------------------------------------------------------- main loop
    def start(self) -> None:
        self.c.start_program(self)
        self._thread.start()

    def _run(self) -> None:
        c = self.c
        c.log(f"program {self.name} started (register offsets int {self.int_offset}, float {self.float_offset})")
        self._write_async_progress(-1)  # reset_async_progress()
        self._signal_ready()
        executing = False
        with c.changed:
            seen = c.handled_input_seq
        try:
            while self.alive:
                with c.changed:
                    while self.alive and c.input_seq == seen:
                        c.changed.wait(0.05)
                    if not self.alive:
                        break
                    seen = c.handled_input_seq = c.input_seq
                    cmd = self._in_int(0)
                if cmd in REALTIME_COMMANDS:
                    keep = self._process(cmd)
                    self._signal_ready()
                elif cmd == 0:
                    executing = False
                    self._signal_ready()
                    keep = True
                else:
                    keep = True
                    if not executing:
                        keep = self._process(cmd)
                    executing = True
                if not keep:
                    break
        except ScriptError as exc:
            c.log(f"runtime error in {self.name}: {exc}")
        finally:
            with c.changed:
                if c.program is self:
                    c.program = None
                    c.runtime_state = RUNTIME_STOPPED
                    c.log(f"program {self.name} ended")
                self.alive = False
                c.changed.notify_all()

    def _transport_delay(self) -> None:
        armed = self.c.faults.take(FaultKind.DELAY) or self.c.faults.peek(FaultKind.SLOW)
        if armed is not None:
            time.sleep(float(armed.params.get("seconds", 0.5)))

    # ----------------------------------------------------------------------------- commands
    def _process(self, cmd: int) -> bool:
        """Run one command; False ends the script (255). Writes 'done' unless 255."""
        self._transport_delay()
        c = self.c
        name = COMMAND_NAMES.get(cmd)
        try:
            if cmd in (1, 2, 3, 4):
                self._move(cmd)
            elif cmd == 17:
                c.set_payload(self._in_double(0), np.array([self._in_double(k) for k in (1, 2, 3)]))
            elif cmd == 65:
                c.set_payload(self._in_double(0), np.array([self._in_double(k) for k in (1, 2, 3)]),
                              np.array([self._in_double(k) for k in range(4, 10)]))
            elif cmd == 29:
                c.set_tcp(self._in_vector(0))
            elif cmd in (30, 46):
                qnear = self._in_vector(6) if cmd == 30 else c.q
                q = self._inverse(self._in_vector(0), qnear)
                self._out_vector(0, q)
            elif cmd == 31:
                c.protective_stop("protective stop requested by the client")
            elif cmd in (33, 34):
                self._stop(cmd)
            elif cmd == 45:
                self._move_path()
            elif cmd in (36, 37):
                self._out_int(1, 1)
            elif cmd == 39:
                self._out_vector(0, kin.pose_trans(self._in_vector(0), self._in_vector(6)))
            elif cmd == 40:
                self._out_vector(0, c.tcp_offset)
            elif cmd == 43:
                self._out_vector(0, kin.forward_pose(c.q, c.tcp_offset))
            elif cmd == 44:
                self._out_vector(0, kin.forward_pose(self._in_vector(0), self._in_vector(6)))
            elif cmd == 47:
                self._out_int(1, 1 if c.is_steady() else 0)
            elif cmd == 58:
                self._out_vector(0, kin.forward_pose(c.q))
            elif cmd in (60, 61):
                qnear = self._in_vector(6) if cmd == 61 else c.q
                try:
                    self._inverse(self._in_vector(0), qnear)
                    self._out_int(1, 1)
                except ScriptError:
                    self._out_int(1, 0)
            elif cmd == 255:
                c.log("stop script received")
                return False
            else:
                # Like the real script's if/elif chain: anything else only gets 'done' (or 'ready').
                c.log(f"command {cmd} ({name or 'unknown'}) is not emulated; answered without action")
        except ScriptError:
            raise
        except RuntimeError as exc:  # e.g. motion refused in a safety stop
            c.log(f"command {cmd} failed: {exc}")
        if cmd not in REALTIME_COMMANDS and self.alive:  # a killed program writes nothing more
            self._signal_done()
        return True

    def _inverse(self, pose, qnear) -> np.ndarray:
        try:
            return kin.inverse(pose6_to_matrix(pose), qnear, self.c.tcp_offset)
        except kin.IKFailed as exc:
            raise ScriptError(f"get_inverse_kin: {exc}") from None

    def _stop_async_move(self) -> None:
        """``stop_async_move()``: kill the move thread and report the operation finished."""
        with self.c.lock:
            if self._async_motion is not None:
                self._async_motion = None
                self.c.detach_callbacks()
                self._write_async_progress(-1)

    def _move(self, cmd: int) -> None:
        c = self.c
        values = self._in_vector(0)
        speed, accel = self._in_double(6), self._in_double(7)
        asynchronous = self._in_int(1) == 1
        if cmd in (1, 2, 4):
            q = values if cmd in (1, 4) else self._inverse(values, c.q)
            if np.any(np.abs(q) > JOINT_LIMIT):
                raise ScriptError(f"joint target {np.round(q, 4).tolist()} is outside ±2π")
        if cmd in (1, 2):
            def factory(t, q0, tcp):
                return Motion("joint", t, q0, tcp, speed=speed, accel=accel, target_q=q)
        else:
            target = kin.forward(values, c.tcp_offset) if cmd == 4 else pose6_to_matrix(values)
            self._inverse(matrix_to_pose6(target), c.q)  # unreachable → runtime error, as on a robot

            def factory(t, q0, tcp):
                return Motion("linear", t, q0, tcp, speed=speed, accel=accel, target_pose=target)

        self._stop_async_move()
        c.log(f"{COMMAND_NAMES[cmd]} {'async ' if asynchronous else ''}to {np.round(values, 5).tolist()} "
              f"v={speed} a={accel}")
        if asynchronous:
            with c.lock:
                self._write_async_progress(0)  # signal_async_operation_started()

                def finished(motion, script=self):
                    with script.c.lock:
                        if script.alive and script._async_motion is motion:
                            script._async_motion = None
                            script._write_async_progress(-1)

                self._async_motion = c.start_motion(factory, finished)
        else:
            motion = c.start_motion(factory)
            c.wait_motion(motion, lambda: self.alive)

    def _move_path(self) -> None:
        """Command 45: run the path injected into ``exec_move_path()`` (``signal_async_progress(i)``
        before the i-th move, as the injected code does), in the move thread when asynchronous."""
        c = self.c
        entries = path_moves(self.path_lines)
        moves = [move for _, move in entries if move is not None]
        if not moves:
            raise ScriptError("move_path: the uploaded script holds no path")
        asynchronous = self._in_int(1) == 1
        self._stop_async_move()
        c.log(f"move_path {'async ' if asynchronous else ''}with {len(moves)} moves")

        def progress(passed: int, script=self) -> None:  # signal_async_progress(passed), in the cycle thread
            if script.alive and passed < len(moves):
                script._write_async_progress(passed)

        if asynchronous:
            with c.lock:
                self._write_async_progress(0)  # signal_async_operation_started()
                self._write_async_progress(0)  # the path's own signal_async_progress(0)

                def finished(motion, script=self):
                    with script.c.lock:
                        if script.alive and script._async_motion is motion:
                            script._async_motion = None
                            script._write_async_progress(-1)

                self._async_motion = self._start_path(moves, finished, progress)
        else:
            self._write_async_progress(0)
            motion = self._start_path(moves, None, progress)
            c.wait_motion(motion, lambda: self.alive)

    def _start_path(self, moves, on_done, progress) -> ArmMotion:
        c = self.c
        plan = plan_path(c, moves)
        motion = c.start_motion(lambda t, q, tcp: Motion("path", t, q, tcp, plan=plan), on_done)
        with c.lock:
            if c.run is not None and c.run.motion is motion:
                c.run.progress = progress
        return motion

    def _stop(self, cmd: int) -> None:
        """``exec_stopl_stopj``: decelerate; synchronously, or in a stop 'thread' when async."""
        c = self.c
        deceleration = self._in_double(0)
        asynchronous = self._in_int(1) == 1
        self._stop_async_move()
        c.log(f"{COMMAND_NAMES[cmd]} a={deceleration} {'async' if asynchronous else ''}")
        if asynchronous:
            with c.lock:
                self._write_async_progress(0)

                def finished(_motion, script=self):
                    if script.alive:
                        script._write_async_progress(-1)

                c.stop_motion(deceleration, finished)
        else:
            motion = c.stop_motion(deceleration)
            if motion is not None:
                c.wait_motion(motion, lambda: self.alive)
