"""RobotSpec registry and the agreement of each spec with its MJCF file (names, limits, rules for pinocchio)."""

from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest

import uniros_async.robots as robots
from uniros_async.errors import ConfigError
from uniros_async.robots import ROBOT_NAMES, RobotSpec, ServoProfile, get_robot_spec, robot_names
from uniros_async.robots.ned2 import NED2
from uniros_async.robots.rx200 import RX200

from ._helpers import arm_actuator_ids, arm_qpos_adr


def test_registry_returns_the_package_specs() -> None:
    assert {"ned2", "rx200"} <= set(ROBOT_NAMES)  # and any robot a user's package registered
    assert robots.ROBOT_NAMES == robot_names()  # read from the registry when asked for
    assert get_robot_spec("rx200") is RX200
    assert get_robot_spec("ned2") is NED2


def test_unknown_robot_lists_valid_names() -> None:
    with pytest.raises(ConfigError, match=r"unknown robot 'ur5'; registered: \[.*'ned2', 'rx200'"):
        get_robot_spec("ur5")
    with pytest.raises(ConfigError, match=r"unknown robot 'rx20' \(did you mean 'rx200'\?\)"):
        get_robot_spec("rx20")


def test_specs_hold_the_documented_numbers() -> None:
    assert RX200.hardware_rate_hz == 10.0 and NED2.hardware_rate_hz == 25.0
    assert RX200.joint_state_names == (
        "waist",
        "shoulder",
        "elbow",
        "wrist_angle",
        "wrist_rotate",
        "gripper",
        "left_finger",
        "right_finger",
    )
    assert NED2.joint_state_names == NED2.arm_joint_names == tuple(f"joint_{i}" for i in range(1, 7))
    assert RX200.servo_profile == ServoProfile(kind="time", move_time_s=2.0, accel_time_s=0.3)
    assert NED2.servo_profile.kind == "velocity"
    assert NED2.servo_profile.max_velocity_rad_s == (1.57, 1.047, 1.57, 3.14, 3.14, 3.14)
    assert NED2.servo_profile.max_acceleration_rad_s2 == (2.0, 0.8, 2.0, 3.0, 3.0, 3.0)
    np.testing.assert_allclose(RX200.joint_upper_rad[1], 1.972222, atol=1e-6)  # shoulder 113 deg
    np.testing.assert_allclose(NED2.joint_lower_rad[1], -1.832596, atol=1e-6)  # joint_2 -105 deg
    assert RX200.hardware_period_s == pytest.approx(0.1) and NED2.n_arm_joints == 6


def test_spec_is_frozen_and_validated() -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        RX200.hardware_rate_hz = 20.0  # type: ignore[misc]
    with pytest.raises(ConfigError, match="home_q_rad of 'shoulder'"):
        dataclasses.replace(RX200, home_q_rad=(0.0, 3.0, 0.0, 0.0, 0.0))
    with pytest.raises(ConfigError, match="joint_lower_rad needs 5 values"):
        dataclasses.replace(RX200, joint_lower_rad=(0.0,))
    with pytest.raises(ConfigError, match="hardware_rate_hz"):
        dataclasses.replace(RX200, hardware_rate_hz=0.0)
    with pytest.raises(ConfigError, match="move_time_s"):
        ServoProfile(kind="time")


def test_mjcf_matches_spec(spec: RobotSpec, mj_model: mujoco.MjModel) -> None:
    """Joint names, ranges, ctrlranges and actuators of the MJCF agree with the spec."""
    assert spec.mjcf_path.is_file()
    adr = arm_qpos_adr(mj_model, spec)
    act = arm_actuator_ids(mj_model, spec)
    for i, name in enumerate(spec.arm_joint_names):
        joint = mj_model.joint(name)
        assert int(joint.type[0]) == int(mujoco.mjtJoint.mjJNT_HINGE)
        np.testing.assert_allclose(joint.range, (spec.joint_lower_rad[i], spec.joint_upper_rad[i]), atol=1e-12)
        actuator = mj_model.actuator(act[i])
        assert int(actuator.trntype[0]) == int(mujoco.mjtTrn.mjTRN_JOINT) and actuator.trnid[0] == joint.id
        assert actuator.ctrllimited[0] and actuator.forcelimited[0]
        np.testing.assert_array_equal(actuator.ctrlrange, joint.range)  # docs/robot-facts.md, pitfall 13
        assert actuator.gainprm[0] > 0 and actuator.biasprm[2] < 0  # a damped position servo
    assert sorted(adr.tolist()) == adr.tolist()
    for name in spec.joint_state_names:  # every joint_states name is an MJCF joint
        mj_model.joint(name)
    assert mj_model.site(spec.ee_site).bodyid[0] > 0
    assert mj_model.body(spec.base_link).parentid[0] == 0
    if spec.gripper_actuator is not None:
        mj_model.actuator(spec.gripper_actuator)
    assert mj_model.opt.timestep == 0.002
    assert int(mj_model.opt.integrator) == int(mujoco.mjtIntegrator.mjINT_IMPLICITFAST)
    mj_model.camera("overview")
    assert mj_model.nlight >= 1


def test_mjcf_follows_the_pinocchio_rules(spec: RobotSpec) -> None:
    """The rules of docs/howto/add-a-robot.md that keep pinocchio's MJCF parser exact (robot-facts.md, pitfalls 1-8)."""
    root = ET.parse(spec.mjcf_path).getroot()
    assert not root.findall(".//frame"), "pinocchio drops bodies inside <frame>"
    for element in root.iter():
        assert "euler" not in element.attrib, f"<{element.tag}> uses euler; write quat"
        assert "axisangle" not in element.attrib and "xyaxes" not in element.attrib
    compiler = root.find("compiler")
    assert compiler is None or "eulerseq" not in compiler.attrib
    bodies = root.findall(".//worldbody//body")
    assert bodies
    for body in bodies:
        assert body.get("name"), "every body is named"
        assert body.find("inertial") is not None, f"body {body.get('name')!r} needs an explicit <inertial>"
    for joint in root.findall(".//worldbody//joint"):
        assert joint.get("name"), "every joint is named"
    roots = root.find("worldbody").findall("body")
    assert [b.get("name") for b in roots] == [spec.base_link]
    base = roots[0]
    assert base.get("pos") is None and base.get("quat") is None and base.find("joint") is None


def test_inertias_are_physical(mj_model: mujoco.MjModel) -> None:
    """No URDF placeholder inertias (0.001 / 0.0015 kg m^2): every radius of gyration is below 0.1 m."""
    for body in range(1, mj_model.nbody):
        mass = mj_model.body_mass[body]
        assert mass > 0
        gyration_radius_m = np.sqrt(mj_model.body_inertia[body].max() / mass)
        assert gyration_radius_m < 0.1, mj_model.body(body).name


def test_arm_geoms_collide_with_table_but_not_with_each_other(mj_model: mujoco.MjModel) -> None:
    table = mj_model.geom("table")
    assert int(table.type[0]) == int(mujoco.mjtGeom.mjGEOM_PLANE) and table.pos[2] == 0.0
    arm = [g for g in range(mj_model.ngeom) if mj_model.geom_bodyid[g] != 0]
    for g in arm:
        assert mj_model.geom_contype[g] & table.conaffinity[0] or table.contype[0] & mj_model.geom_conaffinity[g]
        for h in arm:
            assert not (mj_model.geom_contype[g] & mj_model.geom_conaffinity[h])
