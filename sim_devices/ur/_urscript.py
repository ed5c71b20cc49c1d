"""A small part of URScript: the statements ur_rtde sends besides its control script's registers.

Two kinds of program text reach the twin with motion in it:

- **paths** (``moveL(path)``, ``movePath``): ur_rtde injects the path into its control script, in
  the body of ``exec_move_path()`` (``# inject move path``), as ``signal_async_progress(i)`` and
  ``movel(p[x, y, z, rx, ry, rz],a=..,v=..,r=..)`` lines, re-uploads the script and sends command 45;
- **custom script functions** (``sendCustomScriptFunction``): ``def name():`` with
  ``write_output_integer_register(0 +OFFSET, 1)``, the caller's lines (here ``movec``/``movel``),
  ``write_output_integer_register(0 +OFFSET, 2)``, ``end`` — ur_rtde waits for the 2, then
  re-uploads its control script.

Statements are parsed as Python expressions after turning ``p[...]`` pose literals into calls;
only numbers, lists, the operators + − × / and the calls below are evaluated. ``CustomScript`` runs
a custom function: consecutive motions form one blended path (``_path``), anything else runs when
the motion before it has finished. An unknown function is a runtime error (the program stops), as
on a controller.
"""

from __future__ import annotations

import ast
import re
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from sim_devices._transforms import pose6_to_matrix
from sim_devices.arm import Move, PathError, PathPlan
from sim_devices.ur import _kinematics as kin
from sim_devices.ur._controller import RUNTIME_STOPPED, URController
from sim_devices.ur._motion import Motion

MOTIONS = {"movel", "movep", "movec"}
QUIET = {"textmsg", "sync", "popup"}  # statements without an effect the twin models


class ScriptError(RuntimeError):
    """What makes a real URScript halt with a runtime error (e.g. no IK solution)."""


@dataclass(frozen=True)
class Statement:
    """One call: its function name, positional and keyword arguments (evaluated), and the source line."""

    name: str
    args: tuple[Any, ...]
    kwargs: dict[str, Any]
    line: str


def _evaluate(node: ast.AST) -> Any:
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float, bool)):
        return node.value
    if isinstance(node, ast.Name) and node.id in ("True", "False"):
        return node.id == "True"
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        value = _evaluate(node.operand)
        return -value if isinstance(node.op, ast.USub) else value
    if isinstance(node, ast.BinOp) and isinstance(node.op, (ast.Add, ast.Sub, ast.Mult, ast.Div)):
        left, right = _evaluate(node.left), _evaluate(node.right)
        if isinstance(node.op, ast.Add):
            return left + right
        if isinstance(node.op, ast.Sub):
            return left - right
        return left * right if isinstance(node.op, ast.Mult) else left / right
    if isinstance(node, ast.List):
        return [_evaluate(e) for e in node.elts]
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "_pose":
        return ("pose", [float(_evaluate(a)) for a in node.args])
    raise ScriptError(f"cannot evaluate {ast.dump(node)[:60]}")


def parse_statement(line: str) -> Statement | None:
    """One URScript line as a call, or None for blank lines and comments."""
    text = line.split("#", 1)[0].strip()
    if not text:
        return None
    python = re.sub(r"\bp\[([^\[\]]*)\]", r"_pose(\1)", text)
    try:
        node = ast.parse(python, mode="eval").body
    except SyntaxError:
        raise ScriptError(f"syntax not emulated: {text[:80]!r}") from None
    if not isinstance(node, ast.Call) or not isinstance(node.func, ast.Name):
        raise ScriptError(f"statement not emulated: {text[:80]!r}")
    if node.func.id == "textmsg":  # its arguments may be strings: nothing to evaluate
        return Statement("textmsg", (), {}, text)
    args = tuple(_evaluate(a) for a in node.args)
    kwargs = {k.arg: _evaluate(k.value) for k in node.keywords if k.arg is not None}
    return Statement(node.func.id, args, kwargs, text)


def function_body(program: str, name: str) -> list[str] | None:
    """The lines of ``def name():`` … its ``end`` (matched by indentation), or None if absent."""
    lines = program.split("\n")
    for i, line in enumerate(lines):
        if re.match(rf"\s*def\s+{re.escape(name)}\s*\(\s*\)\s*:", line):
            indent = len(line) - len(line.lstrip())
            body: list[str] = []
            for inner in lines[i + 1:]:
                if inner.strip() == "end" and len(inner) - len(inner.lstrip()) <= indent:
                    return body
                body.append(inner)
            return body
    return None


def _pose(value: Any, what: str) -> np.ndarray:
    if not (isinstance(value, tuple) and value[0] == "pose" and len(value[1]) == 6):
        raise ScriptError(f"{what}: expected a pose p[x, y, z, rx, ry, rz]")
    return pose6_to_matrix(value[1])


def motion_of(statement: Statement) -> Move:
    """A ``movel``/``movep``/``movec`` statement as a path move (URScript defaults: a 1.2, v 0.25, r 0)."""
    name, args, kw = statement.name, list(statement.args), statement.kwargs
    names = ["pose_via", "pose_to", "a", "v", "r", "mode"] if name == "movec" else ["pose", "a", "v", "t", "r"]
    values = dict(zip(names, args))
    values.update(kw)
    if values.get("t", 0):
        raise ScriptError(f"{name} with a time t is not emulated")
    accel, speed, blend = float(values.get("a", 1.2)), float(values.get("v", 0.25)), float(values.get("r", 0.0))
    if name == "movec":
        if int(values.get("mode", 0)) != 0:
            raise ScriptError("movec mode 1 (orientation fixed to the path) is not emulated; use mode 0")
        return Move("circular", _pose(values.get("pose_to"), "movec"), speed, accel, blend,
                    via=_pose(values.get("pose_via"), "movec"))
    return Move("linear", _pose(values.get("pose"), name), speed, accel, blend)


def path_moves(body: list[str]) -> list[tuple[Statement, Move | None]]:
    """``exec_move_path``'s injected lines: the moves (and the progress signals, move None)."""
    out: list[tuple[Statement, Move | None]] = []
    for line in body:
        statement = parse_statement(line)
        if statement is None or statement.name == "textmsg":
            continue
        if statement.name in MOTIONS:
            out.append((statement, motion_of(statement)))
        elif statement.name == "signal_async_progress":
            out.append((statement, None))
        else:
            raise ScriptError(f"{statement.name} in a path is not emulated (only movel, movep and movec)")
    return out


def plan_path(controller: URController, moves: list[Move]) -> PathPlan:
    """``moves`` planned from the current commanded pose; a path the robot cannot follow (overlapping
    blends, a degenerate arc, out of reach at one of a few checked points) is a runtime error."""
    try:
        plan = PathPlan(controller.tcp_pose.copy(), moves)
    except PathError as exc:
        raise ScriptError(str(exc)) from None
    for note in plan.notes:
        controller.log(note)
    q = controller.q
    for index, run in enumerate(plan.runs):
        for s in np.linspace(0.0, run.length, 9):
            try:
                q = kin.inverse(plan.pose(index, float(s)), q, controller.tcp_offset)
            except kin.IKFailed:
                raise ScriptError("the path leaves the robot's reach") from None
    return plan


def run_path(controller: URController, moves: list[Move], alive) -> None:
    """Plan ``moves`` and run them to the end (blocking)."""
    plan = plan_path(controller, moves)
    motion = controller.start_motion(lambda t, q, tcp: Motion("path", t, q, tcp, plan=plan))
    controller.wait_motion(motion, alive)


class CustomScript:
    """A custom script function (``sendCustomScriptFunction``) running on the twin controller."""

    def __init__(self, controller: URController, name: str, body: list[str]) -> None:
        self.c = controller
        self.name = name
        self.statements = [s for s in (parse_statement(line) for line in body) if s is not None]
        self.alive = True
        self._thread = threading.Thread(target=self._run, name=f"ur-script-{name}", daemon=True)

    @classmethod
    def from_program(cls, controller: URController, program: str) -> CustomScript | None:
        """The program as a custom function, or None when it is not one the twin can run."""
        match = re.match(r"\s*def\s+(\w+)\s*\(\s*\)\s*:", program)
        if match is None:
            return None
        body = function_body(program, match.group(1))
        if body is None:
            return None
        try:
            return cls(controller, match.group(1), body)
        except ScriptError as exc:
            controller.log(f"script port: program {match.group(1)!r} not emulated: {exc}")
            return None

    def start(self) -> None:
        self.c.start_program(self)
        self._thread.start()

    def _run(self) -> None:
        c = self.c
        c.log(f"program {self.name} started")
        pending: list[Move] = []
        try:
            for statement in self.statements:
                if not self.alive:
                    break
                if statement.name in MOTIONS:
                    pending.append(motion_of(statement))
                    continue
                if pending:
                    run_path(c, pending, lambda: self.alive)
                    pending = []
                self._execute(statement)
            if pending and self.alive:
                run_path(c, pending, lambda: self.alive)
        except (ScriptError, ValueError, TypeError) as exc:
            c.log(f"runtime error in {self.name}: {exc}")
        finally:
            with c.changed:
                if c.program is self:
                    c.program = None
                    c.runtime_state = RUNTIME_STOPPED
                    c.log(f"program {self.name} ended")
                self.alive = False
                c.changed.notify_all()

    def _execute(self, statement: Statement) -> None:
        c, name, args = self.c, statement.name, statement.args
        if name in QUIET:
            return
        if name in ("write_output_integer_register", "write_output_float_register") and len(args) == 2:
            index = int(args[0])
            with c.changed:
                if name == "write_output_integer_register":
                    c.out_int[index] = int(args[1])
                else:
                    c.out_double[index] = float(args[1])
                c.changed.notify_all()
            return
        if name == "sleep" and len(args) == 1:
            time.sleep(max(0.0, float(args[0])) / c.config.time_scale)
            return
        raise ScriptError(f"{name}() is not emulated")
