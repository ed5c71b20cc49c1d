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

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> URTwinConfig:
        data = checked_fields(cls, data, "UR twin config")
        if "version" in data:
            data["version"] = tuple(int(v) for v in data["version"])
        if "tcp_offset" in data:
            data["tcp_offset"] = [float(v) for v in data["tcp_offset"]]
        config = cls(**data)
        if not config.time_scale > 0:
            raise ValueError(f"UR twin config: time_scale must be > 0, got {config.time_scale}")
        if not 0.0005 <= config.control_period <= 0.1:
            raise ValueError(f"UR twin config: control_period must be 0.5 ms … 100 ms, got {config.control_period}")
        if config.servo_dynamics and not (config.servo_frequency > 0 and 0 < config.servo_damping < 1
                                          and config.following_lag >= 0 and config.settle_tolerance > 0):
            raise ValueError("UR twin config: the servo needs servo_frequency > 0, 0 < servo_damping < 1, "
                             "following_lag ≥ 0 and settle_tolerance > 0")
        if not str(config.serial_number).isdigit():
            raise ValueError("UR twin config: serial_number must be digits")
        return config

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)
