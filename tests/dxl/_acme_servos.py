"""A user's own Dynamixel arm: the servo map of acme_arms' Acme5 (five XL330-M288s), registered from outside
uniros_async as docs/howto/add-a-dynamixel-arm.md shows. ``"dxl._acme_servos:acme5"`` imports it (tests/ is on
the path of every process the tests start)."""

from __future__ import annotations

import acme_arms  # noqa: F401  (registers the robot acme5)

from uniros_async.hardware.dxl.servo_map import ServoConfig, ServoGroup, ServoMap, register_servo_map

ACME5_SERVOS = ServoMap(
    name="acme5",
    robot="acme5",
    servos=(
        ServoConfig(id=11, joint="base_yaw", model="XL330-M288"),
        ServoConfig(id=12, joint="shoulder_pitch", model="XL330-M288", min_position=819, max_position=3333),
        ServoConfig(id=13, joint="elbow_pitch", model="XL330-M288", drive_mode=1, min_position=819, max_position=3106),
        ServoConfig(id=14, joint="wrist_pitch", model="XL330-M288", min_position=910, max_position=3447),
        ServoConfig(id=15, joint="wrist_roll", model="XL330-M288"),
    ),
    groups=(
        ServoGroup(
            name="arm",
            joints=("base_yaw", "shoulder_pitch", "elbow_pitch", "wrist_pitch", "wrist_roll"),
            profile="velocity",
            profile_velocity=60,
            profile_acceleration=20,
        ),
    ),
    baud=1_000_000,
    bus_watchdog_ms=100,
)

register_servo_map(ACME5_SERVOS)
