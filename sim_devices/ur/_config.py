"""Settings of the UR controller twin."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from sim_devices._config import checked_fields


@dataclass
class URTwinConfig:
    """Everything a UR controller twin can be told.

    Attributes
    ----------
    seed : int
        Seeds the repeatability errors (independent of the world's seed streams).
    time_scale : float
        Simulated time runs this many times faster than wall time (moves finish sooner).
    repeatability_translation_std : float
        σ of the attained position error per base axis, metres (default 10 µm).
    repeatability_rotation_std : float
        σ of the attained orientation error per base axis, radians (default 0.001°).
    approach_bias : float
        Systematic position offset along the unit approach direction of the last move, metres
        (a backlash-like overshoot; the same for every visit from the same side).
    thermal_drift_amplitude, thermal_drift_time_constant : float
        Warm-up drift ``A (1 − exp(−t/τ))`` along a seeded base direction, metres and simulated s.
    tcp_offset : list of 6 floats
        TCP offset at power-up (UR pose in the flange frame).
    version : (major, minor, bugfix, build)
        What the controller reports over RTDE and the dashboard.
    serial_number : str
        Digits, answered to ``get serial number``.
    remote_control : bool
        Answer to ``is in remote control`` (the client refuses to connect to a non-loopback
        address that is not in remote control).
    robot_model : str
        Answer to the dashboard's ``get robot model`` (PolyScope 5 names the family: ``UR5``).
    control_period : float
        The controller cycle in wall seconds (0.002: the e-Series' 500 Hz). Every RTDE output
        package of a cycle is built from that cycle's one controller state.
    servo_dynamics : bool
        Model the joint servos (``_servo.py``): ``actual`` lags ``target`` by ``following_lag``
        during motion and rings down after it; a move is done once the residual is below
        ``settle_tolerance``. False: an ideal servo (``actual`` = ``target``).
    servo_frequency, servo_damping, servo_frequency_spread : float
        Natural frequency (Hz), damping ratio, and the seeded relative spread of the frequency
        between joints.
    following_lag : float
        Seconds by which ``actual`` lags ``target`` at constant speed (following error = lag × speed).
    settle_tolerance : float
        Residual joint error (rad) below which a move counts as ended (then ``actual`` = ``target``).
    protective_stop_unlock_delay : float
        Wall seconds after a protective stop before the dashboard may unlock it (PolyScope: 5 s).
    world_publish_period : float
        Wall seconds between intermediate (not settled) flange poses sent to the world.
    max_stream_rate : float or None
        Cap on the RTDE output frequency in Hz (None: honour what the client asks for).
    stop_deceleration : float
        Path deceleration of a protective or emergency stop (m/s² or rad/s²).
    structure_dynamics : bool
        Model the structural modes the encoders do not see (``_dynamics.py``): the TRUE tool lags
        and sags during motion and rings down after it, while the controller reports the move done
        once its encoders have settled. False: the true pose is the encoder pose plus the visit's
        static error.
    structure_frequencies, structure_dampings : six floats each
        Natural frequency (Hz, without payload) and damping ratio of the modes along and about the
        base x, y, z axes.
    structure_lag : float
        Seconds of travel by which the true tool lags the encoders at constant speed (gear
        wind-up; the residual vibration after a stop grows with speed through it).
    structure_inertial_gain : float
        Share of the commanded acceleration that loads the modes (static sag ``g·a/ω²``).
    structure_tilt_gain : float
        Tilt of the tool (rad) per m/s² of linear acceleration, about ``ẑ × a``.
    structure_payload_reference : float
        Payload (kg) that lowers every structural frequency by √2 (``ω / sqrt(1 + m/m_ref)``).
    truth_rate : float
        Samples per simulated second of the dense truth (each move's trajectory record); 0: none.
    truth_tail_tolerance : float
        A move's record ends once the structural residual is below this (m or rad) and the
        encoders are at rest, or when the next move starts.
    truth_tail_max : float
        ... or at the latest this many simulated seconds after the move's profile ended.
    trajectory_dir : str or None
        Where the trajectory files go (``sim_devices.trajectory``); None: kept in memory only.
    """

    seed: int = 0
    time_scale: float = 1.0
    repeatability_translation_std: float = 10e-6
    repeatability_rotation_std: float = float(np.radians(0.001))
    approach_bias: float = 3e-6
    thermal_drift_amplitude: float = 15e-6
    thermal_drift_time_constant: float = 1200.0
    tcp_offset: list[float] = field(default_factory=lambda: [0.0] * 6)
    version: tuple[int, int, int, int] = (5, 15, 0, 0)
    serial_number: str = "20235500123"
    remote_control: bool = True
    robot_model: str = "UR5"
    control_period: float = 0.002
    servo_dynamics: bool = True
    servo_frequency: float = 40.0
    servo_damping: float = 0.8
    servo_frequency_spread: float = 0.1
    following_lag: float = 0.001
    settle_tolerance: float = 1e-6
    protective_stop_unlock_delay: float = 5.0
    world_publish_period: float = 0.02
    max_stream_rate: float | None = None
    stop_deceleration: float = 10.0
    structure_dynamics: bool = True
    structure_frequencies: list[float] = field(default_factory=lambda: [12.0, 13.0, 14.5, 10.0, 11.0, 13.5])
    structure_dampings: list[float] = field(default_factory=lambda: [0.28, 0.25, 0.3, 0.25, 0.27, 0.3])
    structure_lag: float = 40e-6
    structure_inertial_gain: float = 0.06
    structure_tilt_gain: float = 2e-5
    structure_payload_reference: float = 5.0
    truth_rate: float = 1000.0
    truth_tail_tolerance: float = 1e-9
    truth_tail_max: float = 3.0
    trajectory_dir: str | None = None

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> URTwinConfig:
        data = checked_fields(cls, data, "UR twin config")
        if "version" in data:
            data["version"] = tuple(int(v) for v in data["version"])
        if "tcp_offset" in data:
            data["tcp_offset"] = [float(v) for v in data["tcp_offset"]]
        for key in ("structure_frequencies", "structure_dampings"):
            if key in data:
                data[key] = [float(v) for v in data[key]]
        config = cls(**data)
        if not config.time_scale > 0:
            raise ValueError(f"UR twin config: time_scale must be > 0, got {config.time_scale}")
        if not 0.0005 <= config.control_period <= 0.1:
            raise ValueError(f"UR twin config: control_period must be 0.5 ms … 100 ms, got {config.control_period}")
        if config.servo_dynamics and not (config.servo_frequency > 0 and 0 < config.servo_damping < 1
                                          and config.following_lag >= 0 and config.settle_tolerance > 0):
            raise ValueError("UR twin config: the servo needs servo_frequency > 0, 0 < servo_damping < 1, "
                             "following_lag ≥ 0 and settle_tolerance > 0")
        if config.structure_dynamics and not (
                len(config.structure_frequencies) == 6 and len(config.structure_dampings) == 6
                and all(f > 0 for f in config.structure_frequencies)
                and all(0 < z < 1 for z in config.structure_dampings)
                and config.structure_lag >= 0 and config.structure_payload_reference > 0):
            raise ValueError("UR twin config: the structure needs six frequencies > 0, six dampings in (0, 1), "
                             "structure_lag ≥ 0 and structure_payload_reference > 0")
        if not config.truth_rate >= 0 or not config.truth_tail_tolerance > 0 or not config.truth_tail_max > 0:
            raise ValueError("UR twin config: need truth_rate ≥ 0, truth_tail_tolerance > 0 and truth_tail_max > 0")
        if not str(config.serial_number).isdigit():
            raise ValueError("UR twin config: serial_number must be digits")
        return config

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)
