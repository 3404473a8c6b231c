"""The MJCF models: MuJoCo and pinocchio agree, the URDF kinematics are reproduced, and the servos behave."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from uniros_async.kinematics import Kinematics
from uniros_async.robots import RobotSpec

from ._helpers import ROBOT_FACTS, arm_actuator_ids, arm_qpos_adr, random_arm_q, urdf_ee_pose


def _random_full_qpos(model: mujoco.MjModel, rng: np.random.Generator) -> np.ndarray:
    """qpos with every limited joint uniform in its range; unlimited joints keep qpos0."""
    qpos = model.qpos0.copy()
    for j in range(model.njnt):
        if model.jnt_limited[j]:
            qpos[model.jnt_qposadr[j]] = rng.uniform(*model.jnt_range[j])
    return qpos


def test_ee_home_position(spec: RobotSpec, mj_model: mujoco.MjModel) -> None:
    data = mujoco.MjData(mj_model)
    mujoco.mj_resetDataKeyframe(mj_model, data, mj_model.key("home").id)
    data.qpos[arm_qpos_adr(mj_model, spec)] = spec.home_q_rad
    mujoco.mj_kinematics(mj_model, data)
    np.testing.assert_allclose(data.site(spec.ee_site).xpos, ROBOT_FACTS[spec.name].ee_home_m, atol=1e-6)
    np.testing.assert_allclose(data.site(spec.ee_site).xmat.reshape(3, 3), np.eye(3), atol=1e-12)


def test_pinocchio_matches_mujoco_full_model(mj_model: mujoco.MjModel, spec: RobotSpec) -> None:
    """FK of every body and the EE site, mass matrix and gravity agree over 200 random configurations."""
    model = pin.buildModelFromMJCF(str(spec.mjcf_path))
    assert model.nq == mj_model.nq and [model.names[i] for i in range(1, model.njoints)] == [
        mj_model.joint(j).name for j in range(mj_model.njnt)
    ]
    # inertials were parsed: every joint's subtree inertia has mass and the totals agree
    assert all(model.inertias[i].mass > 0 for i in range(1, model.njoints))
    assert sum(model.inertias[i].mass for i in range(model.njoints)) == pytest.approx(mj_model.body_mass.sum())
    data = model.createData()
    mj_data = mujoco.MjData(mj_model)
    site_frame = model.getFrameId(spec.ee_site)
    body_frames = [model.getFrameId(mj_model.body(b).name, pin.FrameType.BODY) for b in range(1, mj_model.nbody)]
    rng = np.random.default_rng(7)
    mass_mj = np.zeros((mj_model.nv, mj_model.nv))
    worst = {"site": 0.0, "rot": 0.0, "body": 0.0, "M": 0.0, "g": 0.0}
    for _ in range(200):
        q = _random_full_qpos(mj_model, rng)
        mj_data.qpos[:] = q
        mj_data.qvel[:] = 0.0
        mujoco.mj_forward(mj_model, mj_data)
        pin.framesForwardKinematics(model, data, q)
        site = data.oMf[site_frame]
        worst["site"] = max(worst["site"], np.abs(site.translation - mj_data.site(spec.ee_site).xpos).max())
        worst["rot"] = max(worst["rot"], np.abs(site.rotation - mj_data.site(spec.ee_site).xmat.reshape(3, 3)).max())
        for b, frame in enumerate(body_frames, start=1):
            worst["body"] = max(worst["body"], np.abs(data.oMf[frame].translation - mj_data.xpos[b]).max())
        mujoco.mj_fullM(mj_model, mj_data, mass_mj)  # the 3.17 signature (m, d, dst); d.qM is gone
        mass_pin = pin.crba(model, data, q)
        mass_pin = np.triu(mass_pin) + np.triu(mass_pin, 1).T
        worst["M"] = max(worst["M"], np.abs(mass_pin - mass_mj).max())
        gravity = pin.computeGeneralizedGravity(model, data, q)
        worst["g"] = max(worst["g"], np.abs(gravity - mj_data.qfrc_bias).max())
    assert worst["site"] < 1e-9 and worst["body"] < 1e-9 and worst["rot"] < 1e-9, worst
    assert worst["M"] < 1e-9 and worst["g"] < 1e-9, worst


def test_mjcf_reproduces_the_urdf_chain(spec: RobotSpec, kin: Kinematics) -> None:
    """The EE pose of the MJCF equals the URDF's (as listed in docs/robot-facts.md) at random configurations."""
    rng = np.random.default_rng(3)
    for _ in range(200):
        q = random_arm_q(spec, rng)
        pos, rot = kin.ee_pose(q)
        urdf_pos, urdf_rot = urdf_ee_pose(ROBOT_FACTS[spec.name], q)
        np.testing.assert_allclose(pos, urdf_pos, atol=1e-9)
        np.testing.assert_allclose(rot, urdf_rot, atol=1e-9)


def test_position_servos_reach_and_hold_targets(spec: RobotSpec, mj_model: mujoco.MjModel, kin: Kinematics) -> None:
    """With ctrl = a target within limits (the move clear of the table), the arm is within 0.02 rad after 1 s."""
    data = mujoco.MjData(mj_model)
    adr = arm_qpos_adr(mj_model, spec)
    act = arm_actuator_ids(mj_model, spec)
    lo, hi = np.array(spec.joint_lower_rad), np.array(spec.joint_upper_rad)
    rng = np.random.default_rng(11)
    done = 0
    for _ in range(200):  # bounded: about a quarter of the candidates pass the clearance filter
        if done == 8:
            break
        target = random_arm_q(spec, rng, margin_rad=0.05)
        start = np.clip(target + rng.uniform(-0.3, 0.3, size=target.shape), lo, hi)
        path = [start + s * (target - start) for s in np.linspace(0.0, 1.0, 11)]
        if min(kin.table_clearance_m(q) for q in path) < 0.02:
            continue  # the move would touch the table: not what this test is about
        mujoco.mj_resetDataKeyframe(mj_model, data, mj_model.key("home").id)
        data.qpos[adr] = start
        data.ctrl[act] = target
        mujoco.mj_forward(mj_model, data)
        mujoco.mj_step(mj_model, data, nstep=round(1.0 / mj_model.opt.timestep))
        error = np.abs(data.qpos[adr] - target)
        assert error.max() < 0.02, (target, error)
        assert data.ncon == 0
        done += 1
    assert done == 8
    assert not any(w.number for w in data.warning)


@pytest.mark.parametrize("case", [0, 1])
def test_table_stops_the_arm(spec: RobotSpec, mj_model: mujoco.MjModel, kin: Kinematics, case: int) -> None:
    """Commanded into the table at full servo torque, no link surface sinks more than 1 cm below z = 0.

    These are step commands without a motion profile: the arm hits the table at up to ~2 rad/s per joint.
    (A sweeping hit at > 3 rad/s, beyond the real servos' velocity limits, can reach ~1.4 cm transiently.)
    """
    target = np.array(ROBOT_FACTS[spec.name].into_table_q[case])
    assert kin.table_clearance_m(target) < -0.04  # the target is inside the table
    data = mujoco.MjData(mj_model)
    adr = arm_qpos_adr(mj_model, spec)
    mujoco.mj_resetDataKeyframe(mj_model, data, mj_model.key("home").id)
    data.ctrl[arm_actuator_ids(mj_model, spec)] = target
    lowest_m, touched = np.inf, False
    for _ in range(750):  # 1.5 s
        mujoco.mj_step(mj_model, data)
        lowest_m = min(lowest_m, kin.table_clearance_m(data.qpos[adr]))
        touched |= data.ncon > 0
    assert touched
    assert lowest_m > -0.01
    assert kin.link_positions(data.qpos[adr])[:, 2].min() > 0.0  # body origins and capsule axes stay above


def test_commands_past_the_limits_are_clipped(spec: RobotSpec, mj_model: mujoco.MjModel) -> None:
    """ctrlrange = joint range: a command 0.5 rad past a limit stops the joint at the limit."""
    data = mujoco.MjData(mj_model)
    adr = arm_qpos_adr(mj_model, spec)
    act = arm_actuator_ids(mj_model, spec)
    lo, hi = np.array(spec.joint_lower_rad), np.array(spec.joint_upper_rad)
    for i in range(spec.n_arm_joints):
        for limit, overshoot in ((lo[i], -0.5), (hi[i], 0.5)):
            mujoco.mj_resetDataKeyframe(mj_model, data, mj_model.key("home").id)
            data.ctrl[act] = spec.home_q_rad
            data.ctrl[act[i]] = limit + overshoot
            mujoco.mj_step(mj_model, data, nstep=750)
            q = data.qpos[adr[i]]
            assert lo[i] - 0.01 <= q <= hi[i] + 0.01, (spec.arm_joint_names[i], limit, q)
            if data.ncon == 0:  # free to move: it got to the limit
                assert abs(q - limit) < 0.02, (spec.arm_joint_names[i], limit, q)


def test_rx200_gripper_fingers_follow_the_actuator() -> None:
    from uniros_async.robots.rx200 import RX200

    model = mujoco.MjModel.from_xml_path(str(RX200.mjcf_path))
    data = mujoco.MjData(model)
    left, right, horn = (model.joint(n).qposadr[0] for n in ("left_finger", "right_finger", "gripper"))
    r, length = 0.014, 0.024  # horn_radius, arm_length of rx200.yaml
    for opening_m in (0.016, 0.03, 0.036):
        mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
        data.ctrl[model.actuator("gripper").id] = opening_m
        mujoco.mj_step(model, data, nstep=250)
        assert data.qpos[left] == pytest.approx(opening_m, abs=1e-3)
        assert data.qpos[right] == pytest.approx(-data.qpos[left], abs=1e-4)
        t = data.qpos[horn]  # crank-slider: finger = r sin(t) + sqrt(L^2 - r^2 cos^2(t))
        assert r * math.sin(t) + math.sqrt(length**2 - (r * math.cos(t)) ** 2) == pytest.approx(
            data.qpos[left], abs=1e-3
        )
