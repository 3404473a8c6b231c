"""Interbotix ReactorX-200 (rx200): the robot spec (numbers from docs/robot-facts.md section 1)."""

from __future__ import annotations

import math

from uniros_async.robots.spec import RobotSpec, ServoProfile, packaged_file

__all__ = ["RX200"]

_PI_OFFSET = 1e-5  # the URDF's pi_offset: waist and wrist_rotate stop 1e-5 rad short of +-pi

RX200 = RobotSpec(
    name="rx200",
    mjcf_path=packaged_file("uniros_async.robots.rx200", "rx200.xml"),
    arm_joint_names=("waist", "shoulder", "elbow", "wrist_angle", "wrist_rotate"),
    # The real arm's joint_states order (xs_sdk): arm, then the gripper horn (rad) and the two fingers (m).
    joint_state_names=(
        "waist",
        "shoulder",
        "elbow",
        "wrist_angle",
        "wrist_rotate",
        "gripper",
        "left_finger",
        "right_finger",
    ),
    joint_lower_rad=(
        -math.pi + _PI_OFFSET,
        math.radians(-108.0),
        math.radians(-108.0),
        math.radians(-100.0),
        -math.pi + _PI_OFFSET,
    ),
    joint_upper_rad=(
        math.pi - _PI_OFFSET,
        math.radians(113.0),
        math.radians(93.0),
        math.radians(123.0),
        math.pi - _PI_OFFSET,
    ),
    # URDF velocity limits (the EEPROM Velocity_Limit 131 is 3.14 rad/s for every servo).
    velocity_limits_rad_s=(math.pi, 1.0, math.pi, math.pi, math.pi),
    hardware_rate_hz=10.0,  # XSHardwareInterface loop_hz
    # Task home: q = 0 puts the EE at (0.408575, 0, 0.30457), the pose of the source paper's reach task.
    home_q_rad=(0.0, 0.0, 0.0, 0.0, 0.0),
    rest_q_rad=(0.0, -1.80, 1.55, 0.8, 0.0),  # sleep_positions of rx200.yaml
    # modes.yaml: arm group in time-based profile, profile_velocity 2000 ms (move time), acceleration 300 ms.
    servo_profile=ServoProfile(kind="time", move_time_s=2.0, accel_time_s=0.3),
    ee_site="ee",  # ee_gripper_link
    base_link="base_link",
    gripper_actuator="gripper",
)
