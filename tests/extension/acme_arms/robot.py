"""The Acme5 arm's RobotSpec; its MJCF model ``acme5.xml`` ships in this package."""

from __future__ import annotations

import math

from uniros_async.robots.spec import RobotSpec, ServoProfile, packaged_file

__all__ = ["ACME5"]

_PI = math.pi - 1e-5  # the waist and wrist roll stop 1e-5 rad short of +-pi, as the MJCF ranges say

ACME5 = RobotSpec(
    name="acme5",
    mjcf_path=packaged_file("acme_arms", "acme5.xml"),
    arm_joint_names=("base_yaw", "shoulder_pitch", "elbow_pitch", "wrist_pitch", "wrist_roll"),
    joint_state_names=("base_yaw", "shoulder_pitch", "elbow_pitch", "wrist_pitch", "wrist_roll"),
    joint_lower_rad=(-_PI, math.radians(-108.0), math.radians(-108.0), math.radians(-100.0), -_PI),
    joint_upper_rad=(_PI, math.radians(113.0), math.radians(93.0), math.radians(123.0), _PI),
    velocity_limits_rad_s=(math.pi, 1.0, math.pi, math.pi, math.pi),
    hardware_rate_hz=20.0,
    home_q_rad=(0.0, 0.0, 0.0, 0.0, 0.0),
    rest_q_rad=(0.0, -1.80, 1.55, 0.8, 0.0),
    servo_profile=ServoProfile(
        kind="velocity", max_velocity_rad_s=(1.5, 1.0, 1.5, 2.0, 2.0), max_acceleration_rad_s2=(4.0, 3.0, 4.0, 6.0, 6.0)
    ),
    ee_site="tool",
    base_link="acme_base",
    gripper_actuator=None,
)
