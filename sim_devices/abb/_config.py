"""Settings of the ABB IRC5 controller twin."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from sim_devices._config import checked_fields


@dataclass
class ABBTwinConfig:
    """Everything an IRC5 twin can be told.

    The physics fields (``seed`` … ``trajectory_dir``) mean what they mean for the UR twin
    (``sim_devices.ur.URTwinConfig``): the same controller core (``sim_devices.arm``) runs both arms.

    Attributes
    ----------
    seed, time_scale : int, float
        Seeds the repeatability errors; simulated time runs ``time_scale`` times faster than wall time.
    repeatability_translation_std, repeatability_rotation_std, approach_bias : float
        The attained-pose error model (m, rad, m), as for the UR twin.
    thermal_drift_amplitude, thermal_drift_time_constant : float
        Warm-up drift ``A (1 − exp(−t/τ))`` (m, simulated s).
    control_period : float
        The controller cycle in wall seconds: 4 ms, the EGM rate (one ``EgmRobot`` per cycle).
    path_acceleration : float
        The TCP acceleration (m/s²) the path planner uses for MoveL/MoveC: nothing on the wire
        carries an acceleration (RAPID's ``AccSet`` is not part of the motion program format).
    joint_acceleration : float
        Joint acceleration (rad/s²) of MoveAbsJ/MoveJ.
    joint_speed_limits : six floats
        Axis speed limits (rad/s) of the IRB 2600 (MoveJ/MoveAbsJ run at ``v_tcp``'s share of them).
    stop_deceleration : float
        Path deceleration of a RAPID stop, guard stop or emergency stop (m/s² or rad/s²).
    servo_*, following_lag, settle_tolerance, structure_*, truth_*, trajectory_dir, world_publish_period
        As for the UR twin.
    username, password : str
        The one RWS user (HTTP Digest, realm ``validusers@robapi.abb``).
    robot_type, rw_version, rw_version_name, controller_id, controller_name, system_name : str
        What ``/rw/system/robottype``, ``/rw/system`` and ``/ctrl/identity`` answer.
    ramdisk_path : str
        The value of ``ctrl/$RAMDISK`` (the motion program client only uses it as a path prefix).
    opmode : str
        ``AUTO`` or ``MANR``: the key switch.
    egm_remote_host, egm_remote_port : str or None, int
        The "UCdevice" transmission protocol's remote address: where EGM packets go (None: the
        twin's own host). EGM streaming starts when a motion program opens (``EGMStreamStart``).
    egm_sample_rate : float
        Seconds between EGM packets (RAPID's ``\\SampleRate:=4``: 4 ms).
    max_sessions : int
        RWS sessions (cookies) the controller keeps; beyond it answers 503 (an IRC5 keeps 70).
    event_log_size : int
        Entries the event log keeps (newest first, as RWS lists them).
    event_log_page : int
        Entries one ``GET rw/elog/0`` answers (the newest; the clients read only the first page).
    """

    seed: int = 0
    time_scale: float = 1.0
    repeatability_translation_std: float = 10e-6
    repeatability_rotation_std: float = float(np.radians(0.001))
    approach_bias: float = 3e-6
    thermal_drift_amplitude: float = 15e-6
    thermal_drift_time_constant: float = 1200.0
    tcp_offset: list[float] = field(default_factory=lambda: [0.0] * 6)
    control_period: float = 0.004
    path_acceleration: float = 2.5
    joint_acceleration: float = 4.0
    joint_speed_limits: list[float] = field(
        default_factory=lambda: [float(v) for v in np.radians([175.0, 175.0, 175.0, 360.0, 360.0, 360.0])])
    stop_deceleration: float = 10.0
    servo_dynamics: bool = True
    servo_frequency: float = 30.0
    servo_damping: float = 0.8
    servo_frequency_spread: float = 0.1
    following_lag: float = 0.001
    settle_tolerance: float = 1e-6
    protective_stop_unlock_delay: float = 0.0
    world_publish_period: float = 0.02
    structure_dynamics: bool = True
    structure_frequencies: list[float] = field(default_factory=lambda: [11.0, 12.0, 13.5, 9.0, 10.0, 12.5])
    structure_dampings: list[float] = field(default_factory=lambda: [0.25, 0.25, 0.3, 0.25, 0.27, 0.3])
    structure_lag: float = 40e-6
    structure_inertial_gain: float = 0.06
    structure_tilt_gain: float = 2e-5
    structure_payload_reference: float = 12.0
    truth_rate: float = 1000.0
    truth_tail_tolerance: float = 1e-9
    truth_tail_max: float = 3.0
    trajectory_dir: str | None = None
    username: str = "Default User"
    password: str = "robotics"
    robot_type: str = "IRB 2600-12/1.65"
    rw_version: str = "6.15.2.0"
    rw_version_name: str = "6.15.02.00"
    controller_id: str = "14-51234"
    controller_name: str = "IRC5-OPR"
    system_name: str = "OPR_IRB2600"
    ramdisk_path: str = "$TEMP"
    opmode: str = "AUTO"
    egm_remote_host: str | None = None
    egm_remote_port: int = 6510
    egm_sample_rate: float = 0.004
    max_sessions: int = 70
    event_log_size: int = 1000
    event_log_page: int = 50

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> ABBTwinConfig:
        data = checked_fields(cls, data, "ABB twin config")
        for key in ("tcp_offset", "structure_frequencies", "structure_dampings", "joint_speed_limits"):
            if key in data:
                data[key] = [float(v) for v in data[key]]
        config = cls(**data)
        if not config.time_scale > 0:
            raise ValueError(f"ABB twin config: time_scale must be > 0, got {config.time_scale}")
        if not 0.001 <= config.control_period <= 0.1:
            raise ValueError(f"ABB twin config: control_period must be 1 ms … 100 ms, got {config.control_period}")
        if not (config.path_acceleration > 0 and config.joint_acceleration > 0 and config.stop_deceleration > 0):
            raise ValueError("ABB twin config: accelerations must be > 0")
        if len(config.joint_speed_limits) != 6 or not all(v > 0 for v in config.joint_speed_limits):
            raise ValueError("ABB twin config: joint_speed_limits must be six speeds > 0 (rad/s)")
        if config.opmode not in ("AUTO", "MANR", "MANF"):
            raise ValueError(f"ABB twin config: opmode must be AUTO, MANR or MANF, got {config.opmode!r}")
        if not config.egm_sample_rate >= config.control_period:
            raise ValueError("ABB twin config: egm_sample_rate must be at least one control period")
        if not 0 < config.egm_remote_port < 65536:
            raise ValueError(f"ABB twin config: egm_remote_port must be a UDP port, got {config.egm_remote_port}")
        return config

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)
