"""The true motion of the UR twin's tool: what the encoders see, plus what they cannot see.

The controller's own view of the arm is its encoders: ``actual_q`` follows the commanded joints
through the joint servos (``_servo``: following lag, a short ring-down), and a move is over — the
blocking ``moveL`` returns, ``isSteady`` turns true — once that view has settled. The TRUE tool
pose adds two things the encoders do not measure:

**Structural modes** (link and gear compliance beyond the encoders). Per base axis — x, y, z and
the rotations about them — a damped oscillator ``d`` driven by the commanded tool motion::

    d̈ + 2 ζ ω ḋ + ω² d = −g · a − ω² (c · v + k · (ẑ × a) [rotation axes only])

with ``a``, ``v`` the commanded linear (rotation axes: angular) acceleration and velocity. Its
static solution is ``d = −(g/ω²) a − c v``: the tool lags the encoders by ``c`` seconds of travel
(friction wind-up of the gears, growing with speed), sags against its acceleration (inertial
load on a compliant structure) and tilts with it (``k``, rad per m/s²). When the motion stops,
whatever deflection it held is released as a damped oscillation at ``ω·sqrt(1 − ζ²)``: the
residual vibration whose stabilisation time and overshoot ISO 9283 asks for. Its amplitude grows
with speed (``c v``) and with payload: each ``ω`` is divided by ``sqrt(1 + m / m_ref)`` (a heavier
tool on the same stiffness rings lower and deflects more, ``g a / ω²``). The encoders never see
it, so the controller reports "done" while the tool is still ringing.

**The visit's static error** (repeatability, approach bias, thermal drift: ``_controller``), which
the structure settles onto; along a move it blends from the previous move's error to the new one
with the path fraction, so the true pose is continuous.

The true TCP is ``(p_enc + e_p + d_p, R(d_r) R(e_r) R_enc)``. It is evaluated on a grid of
``truth_rate`` (simulated) samples per second — several per controller cycle — and written to the
move's trajectory file (``_trajectory``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def rotvec_to_matrix_batch(v: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for (n, 3) rotation vectors → (n, 3, 3): R = I + a·[v]× + b·[v]×², with
    a = sin θ / θ and b = (1 − cos θ) / θ² = 2 sin²(θ/2) / θ² (no cancellation for small θ); below
    θ = 1e-12, a = 1 and b = ½, exact to second order. Written out element by element: it runs on every
    truth sample of the robot twins."""
    v = np.asarray(v, dtype=float)
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    theta2 = x * x + y * y + z * z
    theta = np.sqrt(theta2)
    small = theta < 1e-12
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(theta) / safe)
    half = np.sin(0.5 * theta)
    b = np.where(small, 0.5, 2.0 * half * half / (safe * safe))
    bx, by, bz = b * x, b * y, b * z
    ax, ay, az = a * x, a * y, a * z
    r = np.empty((len(v), 3, 3))
    r[:, 0, 0] = 1.0 + bx * x - b * theta2
    r[:, 1, 1] = 1.0 + by * y - b * theta2
    r[:, 2, 2] = 1.0 + bz * z - b * theta2
    r[:, 0, 1], r[:, 1, 0] = bx * y - az, bx * y + az
    r[:, 0, 2], r[:, 2, 0] = bx * z + ay, bx * z - ay
    r[:, 1, 2], r[:, 2, 1] = by * z - ax, by * z + ax
    return r


def small_rotvec_batch(r: np.ndarray) -> np.ndarray:
    """Rotation vectors of (n, 3, 3) rotations that are small (well below π): from the skew part."""
    w = 0.5 * np.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], axis=1)
    sine = np.linalg.norm(w, axis=1)
    cosine = 0.5 * (np.trace(r, axis1=1, axis2=2) - 1.0)
    angle = np.arctan2(sine, cosine)
    scale = np.where(sine > 1e-15, angle / np.where(sine > 1e-15, sine, 1.0), 1.0)
    return w * scale[:, None]


def matrix_to_quaternion_batch(r: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotations → (n, 4) unit quaternions (w, x, y, z), w ≥ 0 (Shepperd's method: each row
    from its largest component, so none is recovered from a difference of nearly equal numbers)."""
    flat = r.reshape(len(r), 9)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = flat.T
    trace = m00 + m11 + m22
    s21, s02, s10 = m21 - m12, m02 - m20, m10 - m01
    a10, a20, a21 = m10 + m01, m20 + m02, m21 + m12
    candidates = np.stack([  # 4·component² for w, x, y, z
        1.0 + trace, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22])
    pick = candidates.argmax(axis=0)
    rows = np.arange(len(r))
    big = 0.5 * np.sqrt(np.maximum(candidates[pick, rows], 0.0))
    four = 4.0 * big
    # Every row's quaternion for each choice of its largest component, (4 choices, 4 components, n);
    # each row takes the one for its own largest component (one gather instead of a loop of masks).
    options = np.array([
        (big, s21 / four, s02 / four, s10 / four),
        (s21 / four, big, a10 / four, a20 / four),
        (s02 / four, a10 / four, big, a21 / four),
        (s10 / four, a20 / four, a21 / four, big),
    ])
    q = options[pick, :, rows]
    q[q[:, 0] < 0] *= -1.0
    return q


class Structure:
    """The six structural modes (see the module docstring), integrated exactly over steps with the
    forcing held constant.

    Parameters
    ----------
    frequencies, dampings : six floats each
        Natural frequency (Hz, unloaded) and damping ratio of the x, y, z, rx, ry, rz modes.
    lag : float
        ``c``, seconds: the static deflection at constant speed is ``−c · v``.
    inertial_gain : float
        ``g``: the share of the commanded acceleration that loads the modes.
    tilt_gain : float
        ``k``, rad per m/s²: the tool's tilt about ``ẑ × a`` under a linear acceleration ``a``.
    payload_reference : float
        ``m_ref``, kg: the payload that lowers every frequency by √2.
    """

    def __init__(self, frequencies: Sequence[float], dampings: Sequence[float], lag: float, inertial_gain: float,
                 tilt_gain: float, payload_reference: float) -> None:
        self.base_omega = 2.0 * np.pi * np.asarray(frequencies, dtype=float).reshape(6)
        self.zeta = np.asarray(dampings, dtype=float).reshape(6)
        if np.any(self.base_omega <= 0) or np.any(self.zeta <= 0) or np.any(self.zeta >= 1):
            raise ValueError("structure: need frequencies > 0 and 0 < damping < 1 on every axis")
        self.lag = float(lag)
        self.inertial_gain = float(inertial_gain)
        self.tilt_gain = float(tilt_gain)
        self.payload_reference = float(payload_reference)
        self.deflection = np.zeros(6)
        self.rate = np.zeros(6)
        self.set_payload(0.0)

    def set_payload(self, mass: float) -> None:
        self.payload = max(float(mass), 0.0)
        self.omega = self.base_omega / math.sqrt(1.0 + self.payload / self.payload_reference)
        self.sigma = self.zeta * self.omega
        self.omega_d = self.omega * np.sqrt(1.0 - self.zeta**2)

    def forcing(self, velocity: np.ndarray, acceleration: np.ndarray) -> np.ndarray:
        """The right-hand side for commanded (n, 6) velocities and accelerations ([v, ω], [a, α])."""
        a_lin = acceleration[:, :3]
        tilt = np.stack([-a_lin[:, 1], a_lin[:, 0], np.zeros(len(a_lin))], axis=1)  # ẑ × a
        static = self.lag * velocity
        static[:, 3:] += self.tilt_gain * tilt
        return -self.inertial_gain * acceleration - self.omega**2 * static

    def advance(self, forcing: np.ndarray, h: float) -> np.ndarray:
        """Step through (n, 6) forcing values, ``h`` seconds each; returns the (n, 6) deflections."""
        out = np.empty_like(forcing)
        decay = np.exp(-self.sigma * h)
        cos, sin = np.cos(self.omega_d * h), np.sin(self.omega_d * h)
        a11 = decay * (cos + self.sigma / self.omega_d * sin)
        a12 = decay * sin / self.omega_d
        a21 = -decay * self.omega**2 / self.omega_d * sin
        a22 = decay * (cos - self.sigma / self.omega_d * sin)
        omega2 = self.omega**2
        d, v = self.deflection, self.rate
        for j in range(len(forcing)):
            steady = forcing[j] / omega2
            x0 = d - steady
            d = a11 * x0 + a12 * v + steady
            v = a21 * x0 + a22 * v
            out[j] = d
        self.deflection, self.rate = d, v
        return out

    def amplitude(self) -> float:
        """The largest envelope of the six modes (m or rad): how far from rest the structure still is."""
        return float(np.max(np.hypot(self.deflection, self.rate / self.omega)))


class TruthGrid:
    """The commanded tool motion sampled on the truth grid, and its finite-difference velocity and
    acceleration (continued across controller cycles), for the structure's forcing."""

    def __init__(self, pose: np.ndarray) -> None:
        self.position = pose[:3, 3].copy()
        self.rotation = pose[:3, :3].copy()
        self.velocity = np.zeros(6)

    def derivatives(self, positions: np.ndarray, rotations: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
        """Velocities and accelerations (n, 6) of the samples ``positions`` (n, 3), ``rotations`` (n, 3, 3),
        spaced ``h`` seconds after the previous call's last sample."""
        p = np.vstack([self.position[None], positions])
        r = np.concatenate([self.rotation[None], rotations])
        velocity = np.empty((len(positions), 6))
        velocity[:, :3] = np.diff(p, axis=0) / h
        velocity[:, 3:] = small_rotvec_batch(r[1:] @ np.transpose(r[:-1], (0, 2, 1))) / h
        previous = np.vstack([self.velocity[None], velocity])
        acceleration = np.diff(previous, axis=0) / h
        self.position, self.rotation, self.velocity = positions[-1].copy(), rotations[-1].copy(), velocity[-1].copy()
        return velocity, acceleration
