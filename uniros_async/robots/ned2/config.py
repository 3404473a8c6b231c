"""Niryo Ned2: the robot spec (numbers from docs/robot-facts.md section 2)."""

from __future__ import annotations

import math

from uniros_async.robots.spec import RobotSpec, ServoProfile, packaged_file

__all__ = ["NED2"]

_MAX_VELOCITY_RAD_S = (1.57, 1.047, 1.57, 3.14, 3.14, 3.14)  # MoveIt joint_limits.yaml
_MAX_ACCELERATION_RAD_S2 = (2.0, 0.8, 2.0, 3.0, 3.0, 3.0)  # MoveIt joint_limits.yaml

NED2 = RobotSpec(
    name="ned2",
    mjcf_path=packaged_file("uniros_async.robots.ned2", "ned2.xml"),
    arm_joint_names=("joint_1", "joint_2", "joint_3", "joint_4", "joint_5", "joint_6"),
    joint_state_names=("joint_1", "joint_2", "joint_3", "joint_4", "joint_5", "joint_6"),
    joint_lower_rad=tuple(math.radians(d) for d in (-171.88, -105.0, -76.78, -119.75, -110.01, -144.96)),
    joint_upper_rad=tuple(math.radians(d) for d in (171.88, 34.96, 89.96, 119.75, 110.17, 144.96)),
    # MoveIt's limits, which the real arm's trajectories obey; the URDF's (10, 8, 8, 2, 2, 2) exceed the
    # steppers' own v_max (1.571, 1.047, 1.571) for joint_1..3.
    velocity_limits_rad_s=_MAX_VELOCITY_RAD_S,
    hardware_rate_hz=25.0,  # niryo_controllers.yaml hardware_control_loop loop_hz
    # Task home: q = 0 (upper arm vertical, forearm horizontal; EE at (0.2952, 0, 0.42905)). It is mid-range
    # for every joint, puts the EE above the middle of the workspace as q = 0 does for rx200, so both arms
    # start the reach task alike. Niryo's own home (rest_q_rad) is folded low, at 0.20 m height.
    home_q_rad=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    rest_q_rad=(0.0, 0.5, -1.25, 0.0, 0.0, 0.0),  # steppers_params.yaml default_home_position
    servo_profile=ServoProfile(
        kind="velocity", max_velocity_rad_s=_MAX_VELOCITY_RAD_S, max_acceleration_rad_s2=_MAX_ACCELERATION_RAD_S2
    ),
    ee_site="ee",  # tool_link
    base_link="base_link",
    gripper_actuator=None,
)
