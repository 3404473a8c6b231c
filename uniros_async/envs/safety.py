"""Safety checks of a target joint configuration, run by the env loop before anything is sent to the arm."""

from __future__ import annotations

from collections.abc import Iterator

import mujoco
import numpy as np
import pydantic
from pydantic import Field

from uniros_async.config import Bool, ConfigModel, Float, Vec3, key_error
from uniros_async.kinematics import Kinematics
from uniros_async.robots.spec import RobotSpec

__all__ = ["SafetyChecker", "SafetyConfig"]


class SafetyConfig(ConfigModel):
    """Limits of what the env loop will send."""

    table_margin_m: Float = 0.01
    """Every link surface must stay this far above the table plane (z = 0)."""
    workspace_min_m: Vec3 = (-0.05, -0.6, 0.02)
    """Lower corner of the box the EE must stay inside."""
    workspace_max_m: Vec3 = (0.65, 0.6, 0.75)
    """Upper corner of the box the EE must stay inside."""
    max_joint_step_rad: Float = Field(default=0.5, gt=0)
    """The most any joint's command may move per env-loop tick (larger moves are spread over several ticks: a
    rate limiter, not a rejection)."""
    check_self_collision: Bool = True
    """Reject targets where two non-adjacent links collide (MuJoCo collision of the robot's own capsules at the
    target configuration)."""

    @pydantic.model_validator(mode="after")
    def _check(self) -> SafetyConfig:
        lo, hi = self.workspace_min_m, self.workspace_max_m
        if not all(a < b for a, b in zip(lo, hi, strict=True)):
            raise key_error(
                "workspace_max_m", f"must be above workspace_min_m {list(lo)} on every axis, got {list(hi)}"
            )
        return self


class SafetyChecker:
    """Checks targets (``check``) and limits per-tick steps (``limit_step``)."""

    def __init__(self, spec: RobotSpec, kin: Kinematics, config: SafetyConfig | None = None) -> None:
        self.spec = spec
        self.kin = kin
        self.config = config or SafetyConfig()
        self.lower = np.asarray(spec.joint_lower_rad)
        self.upper = np.asarray(spec.joint_upper_rad)
        self._lower_tol, self._upper_tol = self.lower - 1e-9, self.upper + 1e-9  # finite: NaN and inf fail these
        self._model = _model_without_near_pairs(str(spec.mjcf_path))
        self._data = mujoco.MjData(self._model)
        self._qadr = np.array([self._model.joint(n).qposadr[0] for n in spec.arm_joint_names])
        m = self._model
        table = [i for i in range(m.ngeom) if m.geom(i).name == "table"]
        self._table_geoms = set(table)
        # The robot models let arm geoms touch only the world (their capsules are too coarse for dynamics).
        # This private copy lets them touch each other too, for the check alone; geoms of bodies within two
        # kinematic hops always overlap at the joints and are excluded.
        arm = [i for i in range(m.ngeom) if m.geom_bodyid[i] != 0 and i not in self._table_geoms and m.geom_contype[i]]
        for i in arm:
            m.geom_conaffinity[i] |= m.geom_contype[i]
            # the broad phase filters body pairs by the compiled per-body masks (OR of their geoms'), so those
            # must learn the new affinity too, or no arm-arm pair ever reaches the narrow phase
            b = m.geom_bodyid[i]
            m.body_conaffinity[b] |= m.geom_conaffinity[i]
        self._near_mat = np.array([[_hops(m, a, b) <= 2 for b in range(m.nbody)] for a in range(m.nbody)])
        for i in table:  # the table check reads the link poses; contacts with the table are never self-collisions
            m.geom_contype[i] = m.geom_conaffinity[i] = 0
        # geom pairs (a <= b) whose contacts are never a self-collision: the table, bodies within two hops (both
        # also excluded in the model; kept here should a contact slip through), then the pairs that touch at home
        # by construction (e.g. fingers on the gripper bar)
        gb = m.geom_bodyid
        self._ignored = {
            (a, b)
            for a in range(m.ngeom)
            for b in range(a, m.ngeom)
            if a in self._table_geoms or b in self._table_geoms or self._near_mat[gb[a], gb[b]]
        }
        self._allowed = self._contact_pairs(np.asarray(spec.home_q_rad))
        self._ignored |= self._allowed
        self._init_clearance(m)
        self._ee_site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, spec.ee_site)
        self._lower_list: list[float] = self._lower_tol.tolist()
        self._upper_list: list[float] = self._upper_tol.tolist()
        self._ws = (*self.config.workspace_min_m, *self.config.workspace_max_m)
        # views into the private MjData, taken once: every attribute access of MjData builds a new array object
        d = self._data
        self._xpos, self._geom_xpos, self._geom_xmat, self._site_xpos = d.xpos, d.geom_xpos, d.geom_xmat, d.site_xpos
        adr = self._qadr.tolist()
        contiguous = adr == list(range(adr[0], adr[0] + len(adr)))
        self._arm_qpos = d.qpos[adr[0] : adr[0] + len(adr)] if contiguous else None

    def _init_clearance(self, m: mujoco.MjModel) -> None:
        """What the table check reads from MuJoCo's kinematics: the moving bodies' origins and, per collision
        geom of a moving body, how far its surface reaches below its centre along the world z axis.

        The same points as ``Kinematics.link_positions`` (body origins, capsule and cylinder end points with
        their radius, box corners, sphere centres with their radius, other geoms' centres with their bounding
        radius), in closed form: a capsule's lowest end lies ``|R[2, 2]| * half_length`` below its centre, a
        box's lowest corner ``sum_j |R[2, j]| * size_j``, so the check needs no loop over points.
        """
        moving = [b for b in range(1, m.nbody) if int(m.body_weldid[b]) != 0]
        geoms, ext, rad = [], [], []
        for g in range(m.ngeom):
            if int(m.geom_bodyid[g]) not in moving or (m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0):
                continue
            t, size = int(m.geom_type[g]), m.geom_size[g]
            if t in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER)):
                e, r = (0.0, 0.0, float(size[1])), float(size[0])
            elif t == int(mujoco.mjtGeom.mjGEOM_BOX):
                e, r = (float(size[0]), float(size[1]), float(size[2])), 0.0
            elif t == int(mujoco.mjtGeom.mjGEOM_SPHERE):
                e, r = (0.0, 0.0, 0.0), float(size[0])
            else:
                e, r = (0.0, 0.0, 0.0), float(m.geom_rbound[g])
            geoms.append(g)
            ext.append(e)
            rad.append(r)
        self._moving_bodies: list[int] = moving
        self._clear_geoms: list[tuple[int, float, float, float, float]] = [
            (g, *e, r) for g, e, r in zip(geoms, ext, rad, strict=True)
        ]

    def _clearance(self) -> float:
        """The table clearance (m) of the configuration in ``self._data`` (after ``mj_kinematics``).

        On Python floats from one ``tolist`` per array: a handful of floats, and a worker that wakes cold after
        an action cycle pays tens of microseconds for every numpy call (fancy indexing most), little for
        arithmetic in the interpreter loop that every Python process on the machine keeps in cache."""
        body_z = self._xpos.tolist()
        lowest = min(body_z[b][2] for b in self._moving_bodies)
        if self._clear_geoms:
            pos, mat = self._geom_xpos.tolist(), self._geom_xmat.tolist()
            for g, e0, e1, e2, r in self._clear_geoms:
                m = mat[g]
                z = pos[g][2] - abs(m[6]) * e0 - abs(m[7]) * e1 - abs(m[8]) * e2 - r
                if z < lowest:
                    lowest = z
        return float(lowest)

    def _contact_pairs(self, q: np.ndarray) -> set[tuple[int, int]]:
        d, m = self._data, self._model
        d.qpos[:] = m.qpos0
        d.qpos[self._qadr] = q
        mujoco.mj_kinematics(m, d)
        return set(self._collisions())

    def _collisions(self) -> Iterator[tuple[int, int]]:
        """Run ``mj_collision`` on ``self._data`` (after ``mj_kinematics``) and yield each contact's geom pair
        (a <= b) that is not in ``self._ignored``. The usual, safe case has no contact at all (the model excludes
        near bodies and the table), so nothing is converted; else one ``tolist`` of a few pairs."""
        d = self._data
        mujoco.mj_collision(self._model, d)
        n = d.ncon
        if n:
            ignored = self._ignored
            for a, b in d.contact.geom[:n].tolist():
                pair = (a, b) if a <= b else (b, a)
                if pair not in ignored:
                    yield pair

    def check(self, q_target: np.ndarray) -> str | None:
        """None if ``q_target`` is safe to command, else why not (for ``info["unsafe_reason"]``).

        One ``mj_kinematics`` of the checker's own model serves every test (the table clearance from the collision
        geoms' poses, the EE from its site, then ``mj_collision``): the env loop runs this on every action, and in
        a worker woken cold after an action cycle each numpy or pinocchio call costs several times its warm time.
        """
        if q_target.shape != self.lower.shape:
            return f"target of shape {q_target.shape} is not {self.lower.shape} finite values"
        q = q_target.tolist()
        # NaN fails these comparisons, and so does inf (the limits are finite)
        if not all(lo <= x <= hi for lo, x, hi in zip(self._lower_list, q, self._upper_list, strict=True)):
            if not np.isfinite(q_target).all():
                return f"target of shape {q_target.shape} is not {self.lower.shape} finite values"
            return "target outside the joint limits"
        m, d = self._model, self._data
        # the other joints stay at qpos0 (set by _contact_pairs, the only other writer)
        if self._arm_qpos is not None:
            self._arm_qpos[:] = q_target
        else:
            d.qpos[self._qadr] = q_target
        mujoco.mj_kinematics(m, d)
        clearance = self._clearance()  # the table top is the plane z = 0
        if clearance < self.config.table_margin_m:
            return _table_reason(clearance, self.config.table_margin_m)
        x, y, z = self._site_xpos[self._ee_site].tolist()
        x0, y0, z0, x1, y1, z1 = self._ws
        if not (x0 <= x <= x1 and y0 <= y <= y1 and z0 <= z <= z1):
            return f"the end effector would leave the workspace box at {[round(x, 3), round(y, 3), round(z, 3)]}"
        if self.config.check_self_collision:
            pair = next(self._collisions(), None)
            if pair is not None:
                a, b = pair
                return f"self-collision between {m.geom(a).name or a} and {m.geom(b).name or b}"
        return None

    def project(self, q_from: np.ndarray, q_target: np.ndarray) -> np.ndarray | None:
        """The safe part of a move from ``q_from`` (safe) toward an unsafe ``q_target``: joint by joint from the
        base, each joint takes its target value if the configuration stays safe. None when no joint can move.
        At most one check per joint."""
        q = np.array(q_from, dtype=np.float64)
        moved = False
        for j in range(len(q)):
            if q[j] == q_target[j]:
                continue
            trial = q.copy()
            trial[j] = q_target[j]
            if self.check(trial) is None:
                q, moved = trial, True
        return q if moved else None

    def limit_step(self, q_now: np.ndarray, q_target: np.ndarray) -> np.ndarray:
        """The command for this tick: ``q_target``, moved at most ``max_joint_step_rad`` per joint from ``q_now``."""
        step = self.config.max_joint_step_rad
        command: np.ndarray = np.clip(q_target, q_now - step, q_now + step)
        return command


def _model_without_near_pairs(path: str) -> mujoco.MjModel:
    """The MJCF at ``path`` compiled with a contact exclusion for every pair of bodies within two kinematic hops.

    Those pairs always overlap at their joints, so the check ignores their contacts; excluding them in the model
    spares ``mj_collision`` their narrow phase and leaves no contacts to filter in the usual, safe case."""
    spec = mujoco.MjSpec.from_file(path)
    m = spec.compile()
    for a in range(m.nbody):
        for b in range(a + 1, m.nbody):
            if _hops(m, a, b) <= 2:
                ex = spec.add_exclude()
                ex.bodyname1, ex.bodyname2 = m.body(a).name, m.body(b).name
    return spec.compile()


def _hops(m: mujoco.MjModel, a: int, b: int) -> int:
    """Kinematic-tree distance between bodies ``a`` and ``b``."""

    def chain(x: int) -> list[int]:
        out = [x]
        while x != 0:
            x = int(m.body_parentid[x])
            out.append(x)
        return out

    ca, cb = chain(a), chain(b)
    common = next(x for x in ca if x in cb)
    return ca.index(common) + cb.index(common)


def _table_reason(clearance_m: float, margin_m: float) -> str:
    """Why a clearance below the margin is unsafe, in words: a link below the table top, on it, or too close."""
    cm, margin_cm = abs(clearance_m) * 100, margin_m * 100
    if clearance_m < -0.0005:
        where = f"{cm:.1f} cm below the table top"
    elif clearance_m < 0.0005:
        where = "on the table top"
    else:
        where = f"only {cm:.1f} cm above the table"
    return f"a link would be {where} (it must stay {margin_cm:.1f} cm above it)"
