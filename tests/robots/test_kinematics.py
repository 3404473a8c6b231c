"""uniros_async.kinematics against MuJoCo (same MJCF): FK, Jacobian, link points, and position IK."""

from __future__ import annotations

import time

import mujoco
import numpy as np
import pytest

from uniros_async.errors import ConfigError
from uniros_async.kinematics import Kinematics
from uniros_async.robots import RobotSpec

from ._helpers import ROBOT_FACTS, arm_qpos_adr, random_arm_q


def _mj_state(mj_model: mujoco.MjModel, spec: RobotSpec, q: np.ndarray) -> mujoco.MjData:
    data = mujoco.MjData(mj_model)  # qpos0: the rx200 fingers at their reference, as Kinematics locks them
    data.qpos[arm_qpos_adr(mj_model, spec)] = q
    mujoco.mj_kinematics(mj_model, data)
    return data


def test_fk_matches_mujoco_site(spec: RobotSpec, mj_model: mujoco.MjModel, kin: Kinematics) -> None:
    """ee_position / ee_pose equal MuJoCo's site_xpos / site_xmat to 1e-9 over 300 random configurations."""
    rng = np.random.default_rng(0)
    data = mujoco.MjData(mj_model)
    adr = arm_qpos_adr(mj_model, spec)
    site = mj_model.site(spec.ee_site).id
    worst_pos = worst_rot = 0.0
    for _ in range(300):
        q = random_arm_q(spec, rng)
        data.qpos[adr] = q
        mujoco.mj_kinematics(mj_model, data)
        pos, rot = kin.ee_pose(q)
        worst_pos = max(worst_pos, np.abs(pos - data.site_xpos[site]).max())
        worst_pos = max(worst_pos, np.abs(kin.ee_position(q) - data.site_xpos[site]).max())
        worst_rot = max(worst_rot, np.abs(rot - data.site_xmat[site].reshape(3, 3)).max())
    assert worst_pos < 1e-9 and worst_rot < 1e-9, (worst_pos, worst_rot)


def test_ee_home(spec: RobotSpec, kin: Kinematics) -> None:
    np.testing.assert_allclose(kin.ee_position(spec.home_q_rad), ROBOT_FACTS[spec.name].ee_home_m, atol=1e-6)
    np.testing.assert_allclose(kin.home_q_rad, spec.home_q_rad)
    np.testing.assert_allclose(kin.lower_rad, spec.joint_lower_rad, atol=1e-12)
    np.testing.assert_allclose(kin.upper_rad, spec.joint_upper_rad, atol=1e-12)


def test_jacobian_matches_mujoco_and_finite_differences(
    spec: RobotSpec, mj_model: mujoco.MjModel, kin: Kinematics
) -> None:
    rng = np.random.default_rng(1)
    dofs = np.array([mj_model.joint(n).dofadr[0] for n in spec.arm_joint_names])
    jac_mj = np.zeros((3, mj_model.nv))
    for _ in range(50):
        q = random_arm_q(spec, rng, margin_rad=1e-3)
        jac = kin.jacobian(q)
        assert jac.shape == (3, spec.n_arm_joints)
        data = _mj_state(mj_model, spec, q)
        mujoco.mj_comPos(mj_model, data)  # mj_jacSite needs cdof
        mujoco.mj_jacSite(mj_model, data, jac_mj, None, mj_model.site(spec.ee_site).id)
        np.testing.assert_allclose(jac, jac_mj[:, dofs], atol=1e-9)
        step = 1e-6
        numeric = np.stack(
            [(kin.ee_position(q + step * e) - kin.ee_position(q - step * e)) / (2 * step) for e in np.eye(len(q))],
            axis=1,
        )
        np.testing.assert_allclose(jac, numeric, atol=1e-7)


def test_link_positions_match_mujoco(spec: RobotSpec, mj_model: mujoco.MjModel, kin: Kinematics) -> None:
    """Body origins and capsule end points equal MuJoCo's xpos and geom_xpos -+ half-length * geom z axis."""
    rng = np.random.default_rng(2)
    names = kin.link_point_names
    assert len(names) == len(kin.link_point_radii_m) == len(set(names))
    moving = [b for b in range(1, mj_model.nbody) if mj_model.body_weldid[b] != 0]
    assert [n for n in names if ":" not in n] == [mj_model.body(b).name for b in moving]
    for _ in range(50):
        q = random_arm_q(spec, rng)
        points = kin.link_positions(q)
        assert points.shape == (len(names), 3)
        data = _mj_state(mj_model, spec, q)
        expected = []
        for b in moving:
            expected.append(data.xpos[b])
            for g in range(mj_model.ngeom):
                if mj_model.geom_bodyid[g] == b:
                    assert int(mj_model.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_CAPSULE)
                    half = data.geom_xmat[g].reshape(3, 3)[:, 2] * mj_model.geom_size[g, 1]
                    expected += [data.geom_xpos[g] - half, data.geom_xpos[g] + half]
        np.testing.assert_allclose(points, np.array(expected), atol=1e-9)
        assert kin.table_clearance_m(q) == pytest.approx(np.min(points[:, 2] - kin.link_point_radii_m))


def test_table_clearance_at_home_and_in_the_table(spec: RobotSpec, kin: Kinematics) -> None:
    assert kin.table_clearance_m(spec.home_q_rad) > 0.03
    for into_table in ROBOT_FACTS[spec.name].into_table_q:
        assert kin.table_clearance_m(into_table) < -0.04
    assert kin.table_clearance_m(spec.home_q_rad, table_z_m=0.5) < 0.0


def test_ik_solves_reachable_targets_from_a_cold_start(spec: RobotSpec, kin: Kinematics) -> None:
    """>= 99 % of 300 reachable targets (FK of uniform random q) are solved from home, within the limits."""
    rng = np.random.default_rng(42)
    targets = [kin.ee_position(random_arm_q(spec, rng)) for _ in range(300)]
    solved = 0
    durations_s = []
    for target in targets:
        t0 = time.perf_counter()
        q, ok = kin.ik(target, rng=rng)
        durations_s.append(time.perf_counter() - t0)
        assert q.shape == (spec.n_arm_joints,)
        assert np.all(q >= kin.lower_rad) and np.all(q <= kin.upper_rad)
        if ok:
            assert np.linalg.norm(kin.ee_position(q) - target) <= 1e-4
            solved += 1
    # Timing is reported, not asserted: performance is shown by benchmarks.
    print(f"{spec.name}: IK solved {solved}/300, median {np.median(durations_s) * 1e3:.3f} ms")
    assert solved >= 297


def test_ik_warm_start_and_position_free_joint(spec: RobotSpec, kin: Kinematics) -> None:
    """From a nearby start IK converges to the nearby solution, and the last joint (which turns about an axis
    through the EE) keeps its start value."""
    rng = np.random.default_rng(5)
    for _ in range(20):
        q_true = random_arm_q(spec, rng, margin_rad=0.2)
        q0 = q_true + rng.uniform(-0.05, 0.05, size=q_true.shape)
        q, ok = kin.ik(kin.ee_position(q_true), q0)
        assert ok
        assert q[-1] == pytest.approx(q0[-1])  # wrist_rotate / joint_6 cannot move the EE position
        assert np.abs(q[:-1] - q_true[:-1]).max() < 0.1


def test_ik_reports_failure_and_reachability(spec: RobotSpec, kin: Kinematics) -> None:
    far = np.array([2.0, 0.0, 0.3])
    q, ok = kin.ik(far, restarts=2)
    assert not ok and np.all(q >= kin.lower_rad) and np.all(q <= kin.upper_rad)
    assert not kin.is_reachable(far)
    assert not kin.is_reachable((0.0, 0.0, 1.2))
    rng = np.random.default_rng(9)
    assert all(kin.is_reachable(kin.ee_position(random_arm_q(spec, rng))) for _ in range(20))
    # seeded restarts are reproducible
    target = kin.ee_position(random_arm_q(spec, rng))
    np.testing.assert_array_equal(kin.ik(target, rng=3)[0], kin.ik(target, rng=3)[0])


def test_bad_arguments(spec: RobotSpec, kin: Kinematics) -> None:
    with pytest.raises(ValueError, match=f"expected {spec.n_arm_joints} joint angles"):
        kin.ee_position(np.zeros(spec.n_arm_joints + 1))
    with pytest.raises(ConfigError, match="no joint"):
        Kinematics(spec.mjcf_path, ("not_a_joint",))
    with pytest.raises(ConfigError, match="no site"):
        Kinematics(spec.mjcf_path, spec.arm_joint_names, ee_site="nope")
    with pytest.raises(ConfigError, match="base to tip"):
        Kinematics(spec.mjcf_path, tuple(reversed(spec.arm_joint_names)))
    with pytest.raises(ConfigError, match="cannot load MJCF"):
        Kinematics("/nonexistent/robot.xml", spec.arm_joint_names)
