"""RobotSpec: the static description of one arm (joints, limits, rates, home, model file, servo profile).

A spec is plain data with no MuJoCo or pinocchio import, so every layer (sim, envs, cli) can read it cheaply, and
it pickles: a child process gets the spec itself, without importing the package that registered it. Each robot
folder instantiates it once in ``config.py`` (``RX200 = RobotSpec(...)``), next to its MJCF file; a package of
your own does the same with ``packaged_file("my_pkg", "myarm.xml")`` and registers it with
``uniros_async.robots.register_robot``.
"""

from __future__ import annotations

import importlib.resources
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from uniros_async.errors import ConfigError

__all__ = ["RobotSpec", "ServoProfile", "packaged_file"]


def packaged_file(package: str, filename: str) -> Path:
    """Return the filesystem path of a data file shipped inside ``package`` (e.g. an MJCF model).

    Args:
        package: dotted name of a regular package, e.g. ``"uniros_async.robots.rx200"`` or one of your own.
        filename: the file's name inside that package.

    Raises:
        ConfigError: the package is not on the filesystem (e.g. imported from a zip), so MuJoCo cannot open it.
    """
    path = importlib.resources.files(package) / filename
    if not isinstance(path, Path):
        raise ConfigError(f"{package}/{filename} is not a file on disk ({type(path).__name__}); install unzipped")
    return path


@dataclass(frozen=True, kw_only=True)
class ServoProfile:
    """How the robot's own servos shape a position command into a motion (the hardware's defaults).

    Two kinds exist on our arms:

    * ``"time"`` (Dynamixel time-based profile, rx200): each new goal is reached in ``move_time_s``, with
      ``accel_time_s`` of acceleration and deceleration. When an env re-sends a goal every control period,
      the period is the natural move time; ``move_time_s`` is the hardware default (Interbotix modes.yaml).
    * ``"velocity"`` (trapezoid limited per joint, ned2): each joint moves at most at
      ``max_velocity_rad_s`` with at most ``max_acceleration_rad_s2``.

    Attributes:
        kind: ``"time"`` or ``"velocity"``.
        move_time_s: total move time of a time-based profile; 0.0 when ``kind == "velocity"``.
        accel_time_s: acceleration time of a time-based profile; 0.0 when ``kind == "velocity"``.
        max_velocity_rad_s: per-joint velocity bound of a velocity profile, in arm-joint order; empty for "time".
        max_acceleration_rad_s2: per-joint acceleration bound of a velocity profile; empty for "time".
    """

    kind: Literal["time", "velocity"]
    move_time_s: float = 0.0
    accel_time_s: float = 0.0
    max_velocity_rad_s: tuple[float, ...] = ()
    max_acceleration_rad_s2: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.kind == "time":
            if not self.move_time_s > 0.0:
                raise ConfigError(f"ServoProfile(kind='time'): move_time_s must be > 0, got {self.move_time_s}")
            if not 0.0 <= self.accel_time_s <= self.move_time_s / 2:
                raise ConfigError(
                    f"ServoProfile(kind='time'): accel_time_s must be in [0, move_time_s/2], got {self.accel_time_s}"
                )
        elif self.kind == "velocity":
            if len(self.max_velocity_rad_s) != len(self.max_acceleration_rad_s2) or not self.max_velocity_rad_s:
                raise ConfigError(
                    "ServoProfile(kind='velocity'): max_velocity_rad_s and max_acceleration_rad_s2 must be non-empty "
                    f"and of equal length, got {len(self.max_velocity_rad_s)} and {len(self.max_acceleration_rad_s2)}"
                )
            if min(self.max_velocity_rad_s) <= 0.0 or min(self.max_acceleration_rad_s2) <= 0.0:
                raise ConfigError("ServoProfile(kind='velocity'): velocity and acceleration bounds must be > 0")
        else:
            raise ConfigError(f"ServoProfile.kind must be 'time' or 'velocity', got {self.kind!r}")


@dataclass(frozen=True, kw_only=True)
class RobotSpec:
    """Static description of one robot arm; all angles in rad, all vectors in arm-joint order.

    Attributes:
        name: registry name, e.g. ``"rx200"``; also the default topic namespace.
        mjcf_path: the packaged MJCF file; MuJoCo and pinocchio (uniros_async.kinematics) both load it.
        arm_joint_names: the actuated arm joints, base to tip (MJCF joint and actuator names).
        joint_state_names: names of a joint_states message of the real arm, in its order (arm joints first).
        joint_lower_rad: lower position limits of the arm joints.
        joint_upper_rad: upper position limits of the arm joints.
        velocity_limits_rad_s: velocity limits of the arm joints.
        hardware_rate_hz: rate of the robot's hardware control loop (commands are applied at this rate).
        home_q_rad: the task home pose, where reset() returns the arm.
        rest_q_rad: the vendor's folded rest pose (sleep / home position of the real arm).
        servo_profile: the servos' default motion profile.
        ee_site: name of the MJCF site (and pinocchio frame) of the end effector.
        base_link: name of the fixed base body.
        gripper_actuator: name of the gripper's MJCF actuator, or None for an arm without gripper.
    """

    name: str
    mjcf_path: Path
    arm_joint_names: tuple[str, ...]
    joint_state_names: tuple[str, ...]
    joint_lower_rad: tuple[float, ...]
    joint_upper_rad: tuple[float, ...]
    velocity_limits_rad_s: tuple[float, ...]
    hardware_rate_hz: float
    home_q_rad: tuple[float, ...]
    rest_q_rad: tuple[float, ...]
    servo_profile: ServoProfile
    ee_site: str = "ee"
    base_link: str = "base_link"
    gripper_actuator: str | None = None

    def __post_init__(self) -> None:
        n = len(self.arm_joint_names)
        if n == 0:
            raise ConfigError(f"RobotSpec {self.name!r}: arm_joint_names is empty")
        if len(set(self.arm_joint_names)) != n:
            raise ConfigError(f"RobotSpec {self.name!r}: duplicate names in arm_joint_names {self.arm_joint_names}")
        if self.joint_state_names[:n] != self.arm_joint_names:
            raise ConfigError(
                f"RobotSpec {self.name!r}: joint_state_names must start with the arm joints {self.arm_joint_names}, "
                f"got {self.joint_state_names}"
            )
        for field in ("joint_lower_rad", "joint_upper_rad", "velocity_limits_rad_s", "home_q_rad", "rest_q_rad"):
            value = getattr(self, field)
            if len(value) != n:
                raise ConfigError(f"RobotSpec {self.name!r}: {field} needs {n} values, got {len(value)}")
        for j, lo, hi in zip(self.arm_joint_names, self.joint_lower_rad, self.joint_upper_rad, strict=True):
            if not lo < hi:
                raise ConfigError(f"RobotSpec {self.name!r}: joint {j!r} has lower {lo} >= upper {hi}")
        for field in ("home_q_rad", "rest_q_rad"):
            for j, q, lo, hi in zip(
                self.arm_joint_names, getattr(self, field), self.joint_lower_rad, self.joint_upper_rad, strict=True
            ):
                if not lo <= q <= hi:
                    raise ConfigError(f"RobotSpec {self.name!r}: {field} of {j!r} = {q} is outside [{lo}, {hi}]")
        if min(self.velocity_limits_rad_s) <= 0.0:
            raise ConfigError(f"RobotSpec {self.name!r}: velocity limits must be > 0, got {self.velocity_limits_rad_s}")
        if not (math.isfinite(self.hardware_rate_hz) and self.hardware_rate_hz > 0.0):
            raise ConfigError(f"RobotSpec {self.name!r}: hardware_rate_hz must be > 0, got {self.hardware_rate_hz}")
        if self.servo_profile.kind == "velocity" and len(self.servo_profile.max_velocity_rad_s) != n:
            raise ConfigError(
                f"RobotSpec {self.name!r}: servo_profile bounds need {n} values, "
                f"got {len(self.servo_profile.max_velocity_rad_s)}"
            )

    @property
    def n_arm_joints(self) -> int:
        """Number of arm joints (5 for rx200, 6 for ned2)."""
        return len(self.arm_joint_names)

    @property
    def hardware_period_s(self) -> float:
        """Period of the hardware control loop, ``1 / hardware_rate_hz``."""
        return 1.0 / self.hardware_rate_hz
