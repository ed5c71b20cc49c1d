"""Cartesian paths of the UR twin: ``movel``/``movep`` waypoints with blend radii, and ``movec`` arcs.

A program's consecutive moves become one ``PathPlan``: its **runs** are the stretches the tool
travels without stopping (a waypoint with blend radius 0 ends a run: the robot stops there, as a
UR does), each a chain of **pieces** — straight lines, the blends that round the corners, circular
arcs — parameterised by arc length ``s``. A run is driven by one trapezoidal profile (``_motion``).

Blends (UR semantics: the radius ``r`` given with the move *to* waypoint P_i rounds the corner at
P_i): the tool leaves the incoming line ``r`` before P_i and joins the outgoing one ``r`` after it,
on the quadratic Bézier with control point P_i — a parabola, the path of a constant acceleration,
which is how a UR blends linear moves. Its closest approach to P_i is ``(r/2)·sin(φ/2)`` for a
deflection φ. A blend may not overlap its neighbours: ``r`` is at most half of either adjacent
segment (a UR refuses overlapping blends too). Arcs are joined without a blend: a corner at an arc
with r > 0 is blended only when the two pieces are tangent there (two half circles), otherwise
the robot stops at it (logged by the caller).

Speed: a run is travelled at one speed — the least of its moves' speeds, lowered where a blend or
an arc would need more than the run's acceleration (the least of its moves' accelerations) to
turn: at most ``sqrt(a·R)`` on an arc of radius R, and on a blend ``sqrt(a·r·cos²(φ/2)/sin(φ/2))``
(the parabola's sharpest curvature is at its vertex). A real controller slows down only near the
corner; the twin slows the run (simpler, and the same at the corner).

Orientation: knots at the start of each run, at every waypoint (at the middle of its blend) and at
the end, interpolated by slerp in arc length between knots. A ``movec`` (mode 0, "unconstrained")
turns from its start orientation to that of its target; the via point's orientation is not used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from sim_devices._transforms import matrix_to_rotvec, rotvec_to_matrix

TANGENT_TOLERANCE = math.radians(1.0)  # two pieces meeting within this angle need no blend
_BEZIER_TABLE = 257  # samples of a blend's arc-length table


class PathError(ValueError):
    """A path the controller cannot execute (overlapping blends, a degenerate arc ...)."""


class Piece:
    """One piece of a run: positions by arc length ``s`` in [0, length]."""

    length: float

    def position(self, s: float) -> np.ndarray:
        raise NotImplementedError

    def tangent(self, s: float) -> np.ndarray:
        raise NotImplementedError


@dataclass
class Line(Piece):
    start: np.ndarray
    end: np.ndarray

    def __post_init__(self) -> None:
        delta = self.end - self.start
        self.length = float(np.linalg.norm(delta))
        self.direction = delta / self.length if self.length > 0 else np.zeros(3)

    def position(self, s: float) -> np.ndarray:
        return self.start + s * self.direction

    def tangent(self, s: float) -> np.ndarray:
        return self.direction


@dataclass
class Blend(Piece):
    """The quadratic Bézier from ``entry`` to ``exit`` with control point ``corner``."""

    entry: np.ndarray
    corner: np.ndarray
    exit: np.ndarray

    def __post_init__(self) -> None:
        u = np.linspace(0.0, 1.0, _BEZIER_TABLE)
        points = self._at(u)
        steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
        # Chords of 256 steps: the length of a parabola of a few centimetres to well below 1e-9 m.
        self._s = np.concatenate([[0.0], np.cumsum(steps)])
        self._u = u
        self.length = float(self._s[-1])

    def _at(self, u):
        u = np.asarray(u, dtype=float)[..., None]
        return (1 - u) ** 2 * self.entry + 2 * u * (1 - u) * self.corner + u**2 * self.exit

    def _parameter(self, s: float) -> float:
        return float(np.interp(s, self._s, self._u))

    def position(self, s: float) -> np.ndarray:
        return self._at(self._parameter(s))

    def tangent(self, s: float) -> np.ndarray:
        u = self._parameter(s)
        d = 2 * (1 - u) * (self.corner - self.entry) + 2 * u * (self.exit - self.corner)
        return d / np.linalg.norm(d)


@dataclass
class Arc(Piece):
    """A circular arc about ``center``: ``center + radius·(cos φ·e1 + sin φ·e2)``, φ from 0 to ``sweep``."""

    center: np.ndarray
    radius: float
    e1: np.ndarray
    e2: np.ndarray
    sweep: float

    def __post_init__(self) -> None:
        self.length = self.radius * self.sweep

    def position(self, s: float) -> np.ndarray:
        phi = s / self.radius
        return self.center + self.radius * (math.cos(phi) * self.e1 + math.sin(phi) * self.e2)

    def tangent(self, s: float) -> np.ndarray:
        phi = s / self.radius
        return -math.sin(phi) * self.e1 + math.cos(phi) * self.e2

    @classmethod
    def through(cls, start: np.ndarray, via: np.ndarray, end: np.ndarray) -> Arc:
        """The arc from ``start`` through ``via`` to ``end`` (``movec``)."""
        a, b = via - start, end - start
        normal = np.cross(a, b)
        area = float(np.linalg.norm(normal))
        if area < 1e-12 or min(np.linalg.norm(a), np.linalg.norm(b), np.linalg.norm(end - via)) < 1e-6:
            raise PathError("movec: start, via and target must be three distinct points not on one line")
        normal /= area
        # Circumcentre of the triangle start, via, end.
        center = start + (np.dot(a, a) * np.cross(b, np.cross(a, b)) + np.dot(b, b) * np.cross(np.cross(a, b), a)) / (
            2.0 * area**2)
        radius = float(np.linalg.norm(start - center))
        e1 = (start - center) / radius
        e2 = np.cross(normal, e1)  # start → via → end runs counter-clockwise about the normal

        def angle(p):
            return math.atan2(float((p - center) @ e2), float((p - center) @ e1)) % (2 * math.pi)

        return cls(center, radius, e1, e2, angle(end))


@dataclass
class Run:
    """Pieces travelled without a stop, their orientation knots, and the run's speed and acceleration."""

    pieces: list[Piece]
    knots_s: list[float]
    knots_rotation: list[np.ndarray]
    speed: float
    acceleration: float
    waypoint_s: list[float] = field(default_factory=list)  # where each waypoint of the run is passed
    _ends: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._ends = np.cumsum([p.length for p in self.pieces])

    @property
    def length(self) -> float:
        return float(self._ends[-1]) if len(self._ends) else 0.0

    def _piece(self, s: float) -> tuple[Piece, float]:
        i = min(int(np.searchsorted(self._ends, s, side="right")), len(self.pieces) - 1)
        start = float(self._ends[i - 1]) if i > 0 else 0.0
        return self.pieces[i], min(max(s - start, 0.0), self.pieces[i].length)

    def position(self, s: float) -> np.ndarray:
        piece, local = self._piece(s)
        return piece.position(local)

    def rotation(self, s: float) -> np.ndarray:
        knots = self.knots_s
        i = min(max(int(np.searchsorted(knots, s, side="right")) - 1, 0), len(knots) - 2)
        span = knots[i + 1] - knots[i]
        u = 0.0 if span <= 0 else min(max((s - knots[i]) / span, 0.0), 1.0)
        r0, r1 = self.knots_rotation[i], self.knots_rotation[i + 1]
        return rotvec_to_matrix(u * matrix_to_rotvec(r1 @ r0.T)) @ r0


@dataclass
class Move:
    """One statement of a path: ``movel``/``movep`` to ``pose`` (4×4), or ``movec`` through ``via`` to ``pose``."""

    kind: str  # "linear" or "circular"
    pose: np.ndarray
    speed: float
    acceleration: float
    blend: float = 0.0
    via: np.ndarray | None = None


class PathPlan:
    """Consecutive moves from ``start`` (4×4 TCP pose) as runs (see the module docstring).

    ``notes`` lists what the plan changed from the program (a blend dropped at an arc that is not
    tangent), for the controller's log.
    """

    def __init__(self, start: np.ndarray, moves: list[Move]) -> None:
        if not moves:
            raise PathError("a path needs at least one move")
        self.start = np.asarray(start, dtype=float).copy()
        self.moves = moves
        self.notes: list[str] = []
        self.runs: list[Run] = []
        self._build()
        self.length = float(sum(run.length for run in self.runs))
        self.end_pose = moves[-1].pose.copy()

    # ----------------------------------------------------------------------------- building
    def _raw_pieces(self) -> list[Piece]:
        """Each move's own geometry, corner to corner (before blending)."""
        pieces: list[Piece] = []
        here = self.start[:3, 3]
        for index, move in enumerate(self.moves):
            target = move.pose[:3, 3]
            if move.kind == "circular":
                assert move.via is not None
                pieces.append(Arc.through(here, move.via[:3, 3], target))
            else:
                line = Line(here.copy(), target.copy())
                if line.length < 1e-7:
                    raise PathError(f"path: move {index + 1} has no length (pure rotations cannot be part of a path)")
                pieces.append(line)
            here = target
        return pieces

    def _build(self) -> None:
        raw = self._raw_pieces()
        n = len(raw)
        blends = [m.blend for m in self.moves]
        for i, move in enumerate(self.moves):
            if move.speed <= 0 or move.acceleration <= 0 or move.blend < 0:
                raise PathError(f"path: move {i + 1} needs speed > 0, acceleration > 0 and a blend radius >= 0")
        blends[-1] = 0.0  # the last waypoint is where the path ends: the robot stops there
        for i in range(n - 1):
            r = blends[i]
            if r <= 0:
                continue
            a, b = raw[i], raw[i + 1]
            if isinstance(a, Line) and isinstance(b, Line):
                limit = 0.5 * min(a.length, b.length)
                if r > limit + 1e-12:
                    raise PathError(f"path: blend radius {r * 1e3:.3f} mm at waypoint {i + 1} overlaps its neighbours "
                                    f"(at most half of the adjacent segments, {limit * 1e3:.3f} mm)")
            elif _deflection(a.tangent(a.length), b.tangent(0.0)) > TANGENT_TOLERANCE:
                self.notes.append(f"blend at waypoint {i + 1} dropped: an arc meets a piece there at an angle "
                                  "(the twin blends arcs only where they are tangent); the robot stops there")
                blends[i] = 0.0
            else:
                blends[i] = -1.0  # tangent junction: travelled through without a blend piece
        rotations = [self.start[:3, :3]] + [m.pose[:3, :3] for m in self.moves]
        run_pieces: list[Piece] = []
        knots_s, knots_rotation, waypoint_s = [0.0], [rotations[0]], [0.0]
        length = 0.0
        speeds: list[float] = []
        accels: list[float] = []
        turns: list[tuple[float, float]] = []  # (radius, 1/sin-ish factor): speed² ≤ a · radius · factor
        entry_cut = 0.0  # how much of the current raw piece the previous blend took off its start
        for i, piece in enumerate(raw):
            move = self.moves[i]
            speeds.append(move.speed)
            accels.append(move.acceleration)
            exit_cut = blends[i] if i < n - 1 and blends[i] > 0 else 0.0
            trimmed = _trim(piece, entry_cut, exit_cut)
            run_pieces.append(trimmed)
            length += trimmed.length
            if isinstance(piece, Arc):
                turns.append((piece.radius, 1.0))
            if exit_cut > 0:
                nxt = raw[i + 1]
                assert isinstance(piece, Line) and isinstance(nxt, Line)
                corner = piece.end
                half = 0.5 * _deflection(piece.direction, nxt.direction)
                if half > 1e-9:
                    turns.append((exit_cut, math.cos(half) ** 2 / math.sin(half)))
                blend = Blend(corner - exit_cut * piece.direction, corner.copy(), corner + exit_cut * nxt.direction)
                run_pieces.append(blend)
                knots_s.append(length + 0.5 * blend.length)
                waypoint_s.append(length + 0.5 * blend.length)
                length += blend.length
                knots_rotation.append(rotations[i + 1])
                entry_cut = exit_cut
                continue
            entry_cut = 0.0
            knots_s.append(length)
            knots_rotation.append(rotations[i + 1])
            waypoint_s.append(length)
            if i < n - 1 and blends[i] < 0:
                continue  # tangent junction: the run goes on
            accel = min(accels)
            speed = min([*speeds, *(math.sqrt(accel * radius * factor) for radius, factor in turns)])
            self.runs.append(Run(run_pieces, knots_s, knots_rotation, speed, accel, waypoint_s))
            run_pieces, knots_s, knots_rotation, waypoint_s = [], [0.0], [rotations[i + 1]], [0.0]
            length, speeds, accels, turns = 0.0, [], [], []

    # ----------------------------------------------------------------------------- sampling
    def pose(self, run: int, s: float) -> np.ndarray:
        """The 4×4 TCP pose at arc length ``s`` of run ``run``."""
        r = self.runs[run]
        out = np.eye(4)
        out[:3, :3] = r.rotation(s)
        out[:3, 3] = r.position(s)
        return out


def _deflection(a: np.ndarray, b: np.ndarray) -> float:
    return float(math.acos(max(-1.0, min(1.0, float(a @ b)))))


def _trim(piece: Piece, head: float, tail: float) -> Piece:
    """A line without ``head`` metres at its start and ``tail`` at its end (arcs are never trimmed)."""
    if head == 0 and tail == 0:
        return piece
    assert isinstance(piece, Line)
    return Line(piece.start + head * piece.direction, piece.end - tail * piece.direction)
