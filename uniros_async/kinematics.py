"""Arm kinematics with pinocchio, built from the same MJCF file that MuJoCo simulates.

Only the arm joints are free in the kinematic model: every other joint (the rx200 gripper horn and fingers) is
locked at its MJCF reference position (``qpos0``) with ``pinocchio.buildReducedModel``. So ``q`` is always a
vector of the arm joints in the order given (5 for rx200, 6 for ned2), in rad.

Positions are in metres in the world frame of the MJCF (the robot base sits at the origin).

    >>> from uniros_async.kinematics import Kinematics
    >>> from uniros_async.robots import get_robot_spec
    >>> kin = Kinematics.from_spec(get_robot_spec("rx200"))
    >>> kin.ee_position([0, 0, 0, 0, 0]).round(6).tolist()
    [0.408575, 0.0, 0.30457]
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import mujoco
import numpy as np
import numpy.typing as npt
import pinocchio as pin

from uniros_async.errors import ConfigError

if TYPE_CHECKING:
    from uniros_async.robots.spec import RobotSpec

__all__ = ["Kinematics"]

ArrayLike = npt.ArrayLike
FloatArray = npt.NDArray[np.float64]

# IK tuning (position only). Measured on both arms (targets = FK of uniform random q): the first attempt from
# home solves ~96 % (rx200) and ~88 % (ned2) of targets, random restarts the rest (tests/robots checks >= 99 %).
_DAMPING_M = 1e-3  # DLS damping lambda, in metres (the task-space unit)
_MAX_STEP_RAD = 0.5  # largest joint change per iteration; keeps the linearisation honest
_STALL_WINDOW = 8  # iterations over which the error must shrink ...
_STALL_RATIO = 0.7  # ... to at most this fraction, or the attempt is abandoned and restarted


class Kinematics:
    """Forward kinematics, Jacobian, link points and position IK of one arm.

    An instance owns its pinocchio ``Data`` buffers and IK generator: use one instance per thread.

    Args:
        mjcf_path: the MJCF model (the file MuJoCo simulates).
        arm_joint_names: the arm joints, base to tip; all other joints are locked at their MJCF ``qpos0``.
        ee_site: name of the end-effector site in the MJCF.
        home_q_rad: the default IK start; the middle of the joint ranges when None.
        seed: seed of the generator used for IK restarts when ``ik`` gets no ``rng``.

    Raises:
        ConfigError: a joint or the site is missing from the model, or an arm joint is not a 1-DOF joint.
    """

    def __init__(
        self,
        mjcf_path: str | Path,
        arm_joint_names: Sequence[str],
        *,
        ee_site: str = "ee",
        home_q_rad: ArrayLike | None = None,
        seed: int = 0,
    ) -> None:
        path = Path(mjcf_path)
        self.arm_joint_names: tuple[str, ...] = tuple(arm_joint_names)
        self.ee_site = ee_site
        try:
            mj_model = mujoco.MjModel.from_xml_path(str(path))
        except ValueError as exc:  # MuJoCo reports missing files and XML errors as ValueError
            raise ConfigError(f"cannot load MJCF {str(path)!r}: {exc}") from exc
        full = pin.buildModelFromMJCF(str(path))

        # Lock every non-arm joint at MuJoCo's qpos0 (pinocchio's q of a hinge/slide is MuJoCo's qpos,
        # joint ref included, so qpos0 maps over by name).
        missing = [n for n in self.arm_joint_names if not full.existJointName(n)]
        if missing:
            raise ConfigError(f"{path.name}: no joint(s) {missing}; joints are {list(full.names)[1:]}")
        q_lock = pin.neutral(full)
        lock_ids = []
        for jid in range(1, full.njoints):
            name = full.names[jid]
            joint = full.joints[jid]
            if name in self.arm_joint_names:
                if joint.nq != 1 or joint.nv != 1:
                    raise ConfigError(f"{path.name}: arm joint {name!r} must be a hinge or slide (1 DOF)")
                continue
            mj_id = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_JOINT, name)
            if mj_id < 0:
                raise ConfigError(f"{path.name}: pinocchio joint {name!r} is not in the MJCF; name every joint")
            adr = int(mj_model.jnt_qposadr[mj_id])
            q_lock[joint.idx_q : joint.idx_q + joint.nq] = mj_model.qpos0[adr : adr + joint.nq]
            lock_ids.append(jid)
        self.model: pin.Model = pin.buildReducedModel(full, lock_ids, q_lock) if lock_ids else full
        self.data: pin.Data = self.model.createData()
        n = len(self.arm_joint_names)
        idx = [self.model.joints[self.model.getJointId(name)].idx_q for name in self.arm_joint_names]
        if self.model.nq != n or idx != list(range(n)):
            # pinocchio orders joints depth-first, as the MJCF does; q is passed through unpermuted.
            order = [self.model.names[j] for j in range(1, self.model.njoints)]
            raise ConfigError(f"{path.name}: arm_joint_names must be the model's joints base to tip {order}")

        if not self.model.existFrame(ee_site):
            raise ConfigError(f"{path.name}: no site {ee_site!r}")
        self._ee_frame = self.model.getFrameId(ee_site)

        # Limits from MuJoCo's jnt_range: pinocchio 4.1 shifts the limits of joints with a `ref` (it stores
        # range - ref) although its q is MuJoCo's qpos, so MuJoCo is the reference here.
        mj_ids = [mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_JOINT, name) for name in self.arm_joint_names]
        ranges = np.array([mj_model.jnt_range[j] if mj_model.jnt_limited[j] else (-np.pi, np.pi) for j in mj_ids])
        self.lower_rad: FloatArray = ranges[:, 0].copy()
        self.upper_rad: FloatArray = ranges[:, 1].copy()
        mid = 0.5 * (self.lower_rad + self.upper_rad)
        self.home_q_rad: FloatArray = mid if home_q_rad is None else self._as_q(home_q_rad).copy()
        self._lower_list: list[float] = self.lower_rad.tolist()
        self._upper_list: list[float] = self.upper_rad.tolist()
        self._rng = np.random.default_rng(seed)

        self._init_link_points(mj_model)
        self._init_reach(mj_model, mj_ids)
        # Joints that cannot move the EE position (the rx200 wrist_rotate and ned2 joint_6 turn about an axis
        # through the EE site): IK keeps them at their start value instead of randomising them.
        self._position_free = self._find_position_free_joints()

    @classmethod
    def from_spec(cls, spec: RobotSpec, *, seed: int = 0) -> Kinematics:
        """Build the kinematics of a registered robot (its MJCF, arm joints, EE site and home pose)."""
        return cls(spec.mjcf_path, spec.arm_joint_names, ee_site=spec.ee_site, home_q_rad=spec.home_q_rad, seed=seed)

    # ------------------------------------------------------------------ forward kinematics

    @property
    def n_joints(self) -> int:
        """Number of arm joints (the length of every ``q``)."""
        return len(self.arm_joint_names)

    def ee_position(self, q: ArrayLike) -> FloatArray:
        """Return the EE site position (3,) in metres for arm joint angles ``q`` (rad)."""
        self._fk(q)
        return np.array(self.data.oMf[self._ee_frame].translation)

    def ee_pose(self, q: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Return the EE site pose: its position (3,) in m and its rotation matrix (3, 3), both in the world frame."""
        self._fk(q)
        placement = self.data.oMf[self._ee_frame]
        return placement.translation.copy(), placement.rotation.copy()

    def jacobian(self, q: ArrayLike) -> FloatArray:
        """Return the (3, n) position Jacobian of the EE site, world-aligned (d p_ee / d q, m/rad)."""
        self._jacobian(self._as_q(q))
        return np.array(self._jac)

    def link_positions(self, q: ArrayLike) -> FloatArray:
        """Return the (m, 3) world positions of the arm's link points for a table or workspace check.

        The points are the origin of every body that moves with the arm (fixed base excluded) and the end
        points of each collision capsule (box corners, sphere centres for other geoms); names and radii are in
        ``link_point_names`` and ``link_point_radii_m``. A point ``i`` is clear of a plane at height ``h`` when
        ``z_i - link_point_radii_m[i] > h`` (see ``table_clearance_m``).
        """
        pin.forwardKinematics(self.model, self.data, self._as_q(q))
        oMi = self.data.oMi
        placements = np.array([oMi[j].homogeneous[:3] for j in self._point_joints])  # (joints, 3, 4)
        points: FloatArray = np.einsum("kij,kj->ki", placements[self._point_joint_index], self._point_local)
        return points

    def table_clearance_m(self, q: ArrayLike, table_z_m: float = 0.0) -> float:
        """Return the smallest height of any link surface above a horizontal plane at ``table_z_m`` (m).

        Negative means a link (as modelled by its collision capsules) is below the plane.
        """
        points = self.link_positions(q)
        return float(np.min(points[:, 2] - self.link_point_radii_m) - table_z_m)

    # ------------------------------------------------------------------ inverse kinematics

    def ik(
        self,
        target_pos: ArrayLike,
        q0: ArrayLike | None = None,
        *,
        tol: float = 1e-4,
        max_iters: int = 60,
        restarts: int = 30,
        rng: np.random.Generator | int | None = None,
    ) -> tuple[FloatArray, bool]:
        """Solve for arm joint angles that put the EE site at ``target_pos`` (position only), within limits.

        Damped least squares with the joints clamped to their limits; a joint at a limit whose step would
        push it further out is frozen for that step (active set). An attempt that stalls (the error did not
        shrink to 70 % within 8 iterations) or runs out of iterations is restarted from a uniformly random
        ``q`` within the limits. Joints that cannot move the EE position keep their start value.

        Args:
            target_pos: the EE position (3,) in metres.
            q0: the start (e.g. the current joint angles), clipped to the limits; ``home_q_rad`` when None.
            tol: success when the position error is at most this (m).
            max_iters: iterations per attempt.
            restarts: random restarts after the first attempt.
            rng: generator (or seed) for the restarts; the instance's own generator when None.

        Returns:
            (q, success): the best ``q`` found (rad, within limits) and whether its error is within ``tol``.
        """
        target = np.asarray(target_pos, dtype=np.float64).reshape(3)
        gen = self._rng if rng is None else np.random.default_rng(rng)
        start = np.clip(self.home_q_rad if q0 is None else self._as_q(q0), self.lower_rad, self.upper_rad)
        best_q, best_err = start, np.inf
        q_start = start
        for attempt in range(restarts + 1):
            if attempt > 0:
                q_start = gen.uniform(self.lower_rad, self.upper_rad)
                q_start[self._position_free] = start[self._position_free]
            q, err = self._solve(target, q_start, tol, max_iters)
            if err < best_err:
                best_q, best_err = q, err
            if err <= tol:
                return best_q, True
        return best_q, False

    def is_reachable(self, target_pos: ArrayLike, *, tol: float = 1e-4) -> bool:
        """Return whether the EE site can reach ``target_pos`` within the joint limits (to ``tol`` metres).

        Points outside a bounding sphere of the arm are rejected at once; others are decided by ``ik`` with its
        default restarts, so a reachable point is very rarely reported unreachable (0 of 1000 random targets
        per arm in our measurements; the tests require >= 99 %).
        """
        target = np.asarray(target_pos, dtype=np.float64).reshape(3)
        if np.linalg.norm(target - self._reach_center) > self._reach_radius_m + tol:
            return False
        return self.ik(target, tol=tol)[1]

    # ------------------------------------------------------------------ internals

    def _as_q(self, q: ArrayLike) -> FloatArray:
        arr = np.asarray(q, dtype=np.float64).reshape(-1)
        if arr.shape[0] != self.n_joints:
            raise ValueError(f"expected {self.n_joints} joint angles {self.arm_joint_names}, got {arr.shape[0]}")
        return arr

    def _fk(self, q: ArrayLike) -> None:
        pin.framesForwardKinematics(self.model, self.data, self._as_q(q))

    def _jacobian(self, q: FloatArray) -> FloatArray:
        """Run FK and the EE Jacobian at ``q``; return the EE position (a view) and fill ``self._jac``."""
        pin.computeJointJacobians(self.model, self.data, q)
        pin.updateFramePlacement(self.model, self.data, self._ee_frame)
        self._jac = pin.getFrameJacobian(self.model, self.data, self._ee_frame, pin.LOCAL_WORLD_ALIGNED)[:3]
        position: FloatArray = self.data.oMf[self._ee_frame].translation
        return position

    def _solve(self, target: FloatArray, q_start: FloatArray, tol: float, max_iters: int) -> tuple[FloatArray, float]:
        """One DLS attempt from ``q_start``; returns (q, error).

        The per-iteration arithmetic on 3-vectors and n <= 7 joints runs on Python floats: numpy's per-call
        overhead on such small arrays would otherwise dominate the pinocchio work.
        """
        lo, hi = self._lower_list, self._upper_list
        n = self.n_joints
        tx, ty, tz = target.tolist()
        q = q_start.tolist()
        q_arr = np.array(q)
        history: list[float] = []
        for _ in range(max_iters):
            px, py, pz = self._jacobian(q_arr).tolist()
            ex, ey, ez = tx - px, ty - py, tz - pz
            err = math.sqrt(ex * ex + ey * ey + ez * ez)
            if err <= tol:
                return q_arr, err
            history.append(err)
            if len(history) > _STALL_WINDOW and err > _STALL_RATIO * history[-1 - _STALL_WINDOW]:
                return q_arr, err
            jac = self._jac
            dq = _dls_step(jac, ex, ey, ez)
            # Active set: freeze joints at a limit that the step would push further out, then re-solve.
            blocked = [i for i in range(n) if (dq[i] < 0.0 and q[i] <= lo[i]) or (dq[i] > 0.0 and q[i] >= hi[i])]
            if blocked:
                jac = jac.copy()
                jac[:, blocked] = 0.0
                dq = _dls_step(jac, ex, ey, ez)
            step = max(abs(d) for d in dq)
            scale = _MAX_STEP_RAD / step if step > _MAX_STEP_RAD else 1.0
            q = [min(max(qi + scale * di, li), hi_i) for qi, di, li, hi_i in zip(q, dq, lo, hi, strict=True)]
            q_arr = np.array(q)
        px, py, pz = self.ee_position(q_arr).tolist()
        return q_arr, math.sqrt((tx - px) ** 2 + (ty - py) ** 2 + (tz - pz) ** 2)

    def _find_position_free_joints(self) -> npt.NDArray[np.bool_]:
        rng = np.random.default_rng(12345)
        col_norm = np.zeros(self.n_joints)
        for _ in range(16):
            self._jacobian(rng.uniform(self.lower_rad, self.upper_rad))
            col_norm = np.maximum(col_norm, np.linalg.norm(self._jac, axis=0))
        return col_norm < 1e-12

    def _init_link_points(self, mj_model: mujoco.MjModel) -> None:
        names: list[str] = []
        radii: list[float] = []
        joint_local: list[FloatArray] = []
        joint_ids: list[int] = []
        for body in range(1, mj_model.nbody):
            if int(mj_model.body_weldid[body]) == 0:
                continue  # welded to the world: the fixed base never moves
            body_name = mj_model.body(body).name
            frame_id = self.model.getFrameId(body_name, pin.FrameType.BODY)
            if frame_id >= self.model.nframes:
                raise ConfigError(f"body {body_name!r} has no pinocchio frame; name every body in the MJCF")
            local: list[FloatArray] = [np.zeros(3)]
            names.append(body_name)
            radii.append(0.0)
            for geom in range(mj_model.ngeom):
                if int(mj_model.geom_bodyid[geom]) != body:
                    continue
                if mj_model.geom_contype[geom] == 0 and mj_model.geom_conaffinity[geom] == 0:
                    continue  # visual only
                pos = mj_model.geom_pos[geom].copy()
                rot_flat = np.empty(9)
                mujoco.mju_quat2Mat(rot_flat, mj_model.geom_quat[geom])
                rot = rot_flat.reshape(3, 3)
                size = mj_model.geom_size[geom]
                gname = mj_model.geom(geom).name or f"{body_name}/geom{geom}"
                gtype = int(mj_model.geom_type[geom])
                if gtype in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER)):
                    half = rot[:, 2] * size[1]
                    pts, rad = [pos - half, pos + half], float(size[0])
                elif gtype == int(mujoco.mjtGeom.mjGEOM_BOX):
                    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
                    pts, rad = list(pos + (signs * size[:3]) @ rot.T), 0.0
                elif gtype == int(mujoco.mjtGeom.mjGEOM_SPHERE):
                    pts, rad = [pos], float(size[0])
                else:
                    pts, rad = [pos], float(mj_model.geom_rbound[geom])
                for k, p in enumerate(pts):
                    local.append(np.asarray(p, dtype=np.float64))
                    names.append(f"{gname}:{k}")
                    radii.append(rad)
            # Express the points in the frame of the body's parent joint once, so link_positions needs only
            # the joint placements (forwardKinematics), not every frame.
            frame = self.model.frames[frame_id]
            joint_local.extend(frame.placement.act(p) for p in local)
            joint_ids.extend([int(frame.parentJoint)] * len(local))
        self.link_point_names: tuple[str, ...] = tuple(names)
        self.link_point_radii_m: FloatArray = np.array(radii)
        self._point_joints = sorted(set(joint_ids))
        self._point_joint_index = np.array([self._point_joints.index(j) for j in joint_ids])
        self._point_local = np.hstack([np.array(joint_local), np.ones((len(joint_local), 1))])  # homogeneous

    def _init_reach(self, mj_model: mujoco.MjModel, mj_ids: list[int]) -> None:
        """A sphere that contains every reachable EE position: centred on the first arm joint's anchor."""
        mj_data = mujoco.MjData(mj_model)
        mujoco.mj_kinematics(mj_model, mj_data)
        anchors = [mj_data.xanchor[j].copy() for j in mj_ids]
        site = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_SITE, self.ee_site)
        if site < 0:
            raise ConfigError(f"no site {self.ee_site!r} in the MJCF")
        chain = [*anchors, mj_data.site_xpos[site].copy()]
        self._reach_center = anchors[0]
        self._reach_radius_m = float(sum(np.linalg.norm(b - a) for a, b in zip(chain[:-1], chain[1:], strict=True)))


def _dls_step(jac: FloatArray, ex: float, ey: float, ez: float) -> list[float]:
    """Damped least-squares step ``J^T (J J^T + lambda^2 I)^-1 e`` for a (3, n) Jacobian, as a list of floats."""
    (a, b, c), (_, d, e), (_, _, f) = (jac @ jac.T).tolist()
    lam2 = _DAMPING_M * _DAMPING_M
    a += lam2
    d += lam2
    f += lam2
    # Inverse of the symmetric 3x3 matrix [[a b c] [b d e] [c e f]] by cofactors (it is positive definite).
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    inv_det = 1.0 / (a * c00 + b * c01 + c * c02)
    w0 = (c00 * ex + c01 * ey + c02 * ez) * inv_det
    w1 = (c01 * ex + c11 * ey + c12 * ez) * inv_det
    w2 = (c02 * ex + c12 * ey + c22 * ez) * inv_det
    j0, j1, j2 = jac.tolist()
    return [w0 * x + w1 * y + w2 * z for x, y, z in zip(j0, j1, j2, strict=True)]
