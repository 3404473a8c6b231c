"""Helpers and per-robot reference data shared by the robot tests.

To test a new robot, register it (uniros_async.robots) and add its entry to ROBOT_FACTS below; every test in
tests/robots is parametrized over the registered robots.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import mujoco
import numpy as np

from uniros_async.robots import RobotSpec

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class RobotFacts:
    """Independent reference data of one robot (from docs/robot-facts.md, not from our MJCF).

    Attributes:
        ee_home_m: EE site position at ``home_q_rad``.
        urdf_joints: the URDF arm joints base to tip as (origin xyz, origin rpy, axis).
        urdf_ee: the fixed joints from the last arm link to the EE frame as (origin xyz, origin rpy).
        into_table_q: two arm targets inside the table (the arm must be stopped by it).
    """

    ee_home_m: Vec3
    urdf_joints: tuple[tuple[Vec3, Vec3, Vec3], ...]
    urdf_ee: tuple[tuple[Vec3, Vec3], ...]
    into_table_q: tuple[tuple[float, ...], tuple[float, ...]]


_HALF_PI = math.pi / 2

ROBOT_FACTS: dict[str, RobotFacts] = {
    "rx200": RobotFacts(
        ee_home_m=(0.408575, 0.0, 0.30457),
        urdf_joints=(
            ((0, 0, 0.06566), (0, 0, 0), (0, 0, 1)),  # waist
            ((0, 0, 0.03891), (0, 0, 0), (0, 1, 0)),  # shoulder
            ((0.05, 0, 0.2), (0, 0, 0), (0, 1, 0)),  # elbow
            ((0.2, 0, 0), (0, 0, 0), (0, 1, 0)),  # wrist_angle
            ((0.065, 0, 0), (0, 0, 0), (1, 0, 0)),  # wrist_rotate
        ),
        # ee_arm, ee_bar (gripper_bar is the identity), ee_gripper
        urdf_ee=(((0.043, 0, 0), (0, 0, 0)), ((0.023, 0, 0), (0, 0, 0)), ((0.027575, 0, 0), (0, 0, 0))),
        into_table_q=((0.0, 1.97, 0.0, 0.0, 0.0), (0.0, 0.5, 1.62, 0.0, 0.0)),
    ),
    "ned2": RobotFacts(
        ee_home_m=(0.2952, 0.0, 0.42905),
        urdf_joints=(
            ((0, 0, 0.1013), (0, 0, 0), (0, 0, 1)),
            ((0, 0, 0.065), (_HALF_PI, 0, 0), (0, 0, 1)),
            ((0.012, 0.221, 0), (0, 0, _HALF_PI), (0, 0, 1)),
            ((0.0325, -0.065, 0), (_HALF_PI, 0, 0), (0, 0, 1)),
            ((0, 0, 0.17), (-_HALF_PI, 0, 0), (0, 0, 1)),
            ((0.00925, -0.0197, 0), (_HALF_PI, 0, 0), (0, 0, 1)),
        ),
        urdf_ee=(((0, 0, 0.0285), (math.pi, -_HALF_PI, 0)),),  # hand_tool_joint
        into_table_q=((0.0, -1.83, 0.0, 0.0, 0.0, 0.0), (0.0, -1.83, 0.0, 0.0, 1.9, 0.0)),
    ),
}


# acme5, the arm of a user's own package (tests/extension/acme_arms), is the rx200's kinematic chain under other
# names and without the gripper: the rx200's URDF facts are its reference. Without fingers, the rx200's second
# table target stops 2.9 cm short of 4 cm deep; the wrist turned down takes the tool 4.4 cm into the table.
ROBOT_FACTS["acme5"] = dataclasses.replace(
    ROBOT_FACTS["rx200"], into_table_q=((0.0, 1.97, 0.0, 0.0, 0.0), (0.0, 0.5, 1.62, -0.5, 0.0))
)


def arm_qpos_adr(model: mujoco.MjModel, spec: RobotSpec) -> np.ndarray:
    """qpos addresses of the arm joints, in spec order."""
    return np.array([model.joint(name).qposadr[0] for name in spec.arm_joint_names])


def arm_actuator_ids(model: mujoco.MjModel, spec: RobotSpec) -> np.ndarray:
    """Actuator ids of the arm joints (actuators are named after their joint), in spec order."""
    return np.array([model.actuator(name).id for name in spec.arm_joint_names])


def random_arm_q(spec: RobotSpec, rng: np.random.Generator, margin_rad: float = 0.0) -> np.ndarray:
    """A uniformly random arm configuration within the limits shrunk by ``margin_rad``."""
    lo = np.array(spec.joint_lower_rad) + margin_rad
    hi = np.array(spec.joint_upper_rad) - margin_rad
    return rng.uniform(lo, hi)


def rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """URDF fixed-axis roll-pitch-yaw: Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr, cp, sp, cy, sy = (f(a) for a in (roll, pitch, yaw) for f in (math.cos, math.sin))
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by ``angle`` about the unit vector ``axis`` (Rodrigues)."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def urdf_ee_pose(facts: RobotFacts, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """EE position and rotation of the URDF chain in ``facts`` at arm angles ``q`` (plain numpy)."""
    rot, pos = np.eye(3), np.zeros(3)
    for (xyz, rpy, axis), angle in zip(facts.urdf_joints, q, strict=True):
        pos = pos + rot @ np.array(xyz, dtype=float)
        rot = rot @ rpy_matrix(*rpy) @ axis_angle_matrix(np.array(axis, dtype=float), angle)
    for xyz, rpy in facts.urdf_ee:
        pos = pos + rot @ np.array(xyz, dtype=float)
        rot = rot @ rpy_matrix(*rpy)
    return pos, rot
