"""The safety checker on its own: each kind of refusal fires, with MuJoCo's real collision pipeline."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from uniros_async.envs.safety import SafetyChecker, SafetyConfig
from uniros_async.kinematics import Kinematics
from uniros_async.robots import get_robot_spec

# configurations where two non-adjacent links interpenetrate by centimetres while every link stays above the
# table and the EE inside the workspace (found by sampling the joint space with mj_geomDistance)
FOLDED = {
    "rx200": [-2.99, 0.71, 1.34, 1.47, 2.42],
    "ned2": [1.52, -1.55, -1.23, 1.44, -0.39, 1.26],
}


def _checker(arm: str, **kw: object) -> SafetyChecker:
    spec = get_robot_spec(arm)
    return SafetyChecker(spec, Kinematics.from_spec(spec), SafetyConfig(**kw))  # type: ignore[arg-type]


@pytest.mark.parametrize("arm", sorted(FOLDED))
def test_self_collision_is_refused(arm: str) -> None:
    q = np.asarray(FOLDED[arm])
    checker = _checker(arm)
    m, d = checker._model, checker._data
    d.qpos[:] = m.qpos0
    d.qpos[checker._qadr] = q
    mujoco.mj_kinematics(m, d)
    arm_geoms = [i for i in range(m.ngeom) if m.geom_bodyid[i] != 0 and m.geom(i).name != "table"]
    deepest = min(
        mujoco.mj_geomDistance(m, d, a, b, 0.5, None)
        for a in arm_geoms
        for b in arm_geoms
        if a < b and not checker._near_mat[m.geom_bodyid[a], m.geom_bodyid[b]]
    )
    assert deepest < -0.01, "the fixture must really interpenetrate"
    why = checker.check(q)
    assert why is not None and why.startswith("self-collision between"), why
    # the same target passes every other check: only the self-collision check refuses it
    assert _checker(arm, check_self_collision=False).check(q) is None


@pytest.mark.parametrize("arm", sorted(FOLDED))
def test_home_and_random_safe_targets_pass(arm: str) -> None:
    checker = _checker(arm)
    spec = checker.spec
    assert checker.check(np.asarray(spec.home_q_rad)) is None
    rng = np.random.default_rng(0)
    reasons = {
        (checker.check(q) or "ok").split(" ")[0]
        for q in rng.uniform(checker.lower, checker.upper, (400, len(checker.lower)))
    }
    assert {"ok", "self-collision", "a", "the"} <= reasons, reasons  # safe, self-collision, table, workspace


def test_table_joint_limit_and_bad_shape() -> None:
    checker = _checker("rx200")
    assert "table" in (checker.check(np.array([0.0, 1.9, 1.5, 1.5, 0.0])) or "")
    assert "joint limits" in (checker.check(np.array([0.0, 0.0, 0.0, 0.0, 3.5])) or "")
    assert "shape" in (checker.check(np.zeros(4)) or "")
    assert "finite" in (checker.check(np.full(5, np.nan)) or "")


def _reference_reason(checker: SafetyChecker, q: np.ndarray) -> str | None:
    """The check spelled out with the pinocchio kinematics (link points, EE frame) and the contact filter of
    ``_contact_pairs``: what ``check``'s single MuJoCo pass must agree with."""
    if not ((q >= checker.lower - 1e-9).all() and (q <= checker.upper + 1e-9).all()):
        return "limits"
    if checker.kin.table_clearance_m(q) < checker.config.table_margin_m:
        return "table"
    ee = checker.kin.ee_position(q)
    if np.any(ee < checker.config.workspace_min_m) or np.any(ee > checker.config.workspace_max_m):
        return "workspace"
    # every contact of the checker's model at q, filtered here on its own: not the table, not bodies within two
    # hops, not a pair that touches at home
    m, d = checker._model, checker._data
    d.qpos[:] = m.qpos0
    d.qpos[checker._qadr] = q
    mujoco.mj_kinematics(m, d)
    mujoco.mj_collision(m, d)
    for a, b in d.contact.geom[: d.ncon].tolist():
        a, b = min(a, b), max(a, b)
        if "table" in (m.geom(a).name, m.geom(b).name) or checker._near_mat[m.geom_bodyid[a], m.geom_bodyid[b]]:
            continue
        if (a, b) not in checker._allowed:
            return "self-collision"
    return None


@pytest.mark.parametrize("arm", sorted(FOLDED))
def test_check_agrees_with_the_pinocchio_reference(arm: str) -> None:
    checker = _checker(arm)
    rng = np.random.default_rng(1)
    seen = set()
    for q in rng.uniform(checker.lower - 0.1, checker.upper + 0.1, (1500, len(checker.lower))):
        why = checker.check(q)
        kind = None
        if why is not None:
            kind = next(k for k in ("limits", "table", "workspace", "self-collision") if k in why)
        assert kind == _reference_reason(checker, q), (q.tolist(), why)
        seen.add(kind)
    assert seen == {None, "limits", "table", "workspace", "self-collision"}, seen
    # the closed-form clearance and the site position equal the pinocchio link points and EE frame
    for q in rng.uniform(checker.lower, checker.upper, (100, len(checker.lower))):
        checker._data.qpos[checker._qadr] = q
        mujoco.mj_kinematics(checker._model, checker._data)
        assert checker._clearance() == pytest.approx(checker.kin.table_clearance_m(q), abs=1e-9)
        np.testing.assert_allclose(checker._data.site_xpos[checker._ee_site], checker.kin.ee_position(q), atol=1e-9)


def test_the_table_reason_reads_naturally() -> None:
    from uniros_async.envs.safety import _table_reason

    assert _table_reason(-0.301, 0.02) == "a link would be 30.1 cm below the table top (it must stay 2.0 cm above it)"
    assert _table_reason(0.0, 0.02) == "a link would be on the table top (it must stay 2.0 cm above it)"
    assert _table_reason(0.012, 0.02) == "a link would be only 1.2 cm above the table (it must stay 2.0 cm above it)"
    why = _checker("rx200").check(np.array([0.0, 1.9, 1.5, 1.5, 0.0])) or ""
    assert "below the table top" in why and "-" not in why, why
