"""SceneLogger: bus messages to Rerun entities, the same for a live domain and for a bag.

- ``/<ns>/joint_states`` (JointState): the arm ``arms/<ns>``, its geoms posed by MuJoCo forward kinematics of the
  arm's MJCF (the robot registered as ``<ns>``, or the one whose joint names the state carries), the end effector's
  trail, and a measured curve per joint under ``joints/<ns>/<joint>/measured``;
- ``/<ns>/command`` (JointCommand): the commanded curve beside it, ``joints/<ns>/<joint>/commanded``;
- Marker topics: ``markers/<topic>/<marker ns>/<id>``, removed at ``action="delete"`` and ``lifetime_s`` after
  their stamp;
- Image topics: ``cameras/<topic>``.

Every entity is logged at its message's time on the ``time`` timeline (seconds of the domain's clock, or the
bag's log time), so a bag's view has a time slider.
"""

from __future__ import annotations

import collections
import logging
from typing import Any

import numpy as np

from uniros_async.bus.messages import Image, JointCommand, JointState, Marker

__all__ = ["ArmGeoms", "SceneLogger"]

logger = logging.getLogger(__name__)

TRAIL_LENGTH = 200
"""End-effector positions kept in an arm's trail."""

ARM_EYE = ((0.65, -0.65, 0.5), (0.1, 0.0, 0.15))
"""Where the 3D view looks from and at (m, world): an arm at the origin, its reach in front."""


class ArmGeoms:
    """An arm's MuJoCo model, posed from joint positions: its geoms as Rerun capsules, boxes and spheres."""

    def __init__(self, robot: str) -> None:
        import mujoco

        from uniros_async.robots import get_robot_spec

        self.spec = get_robot_spec(robot)
        self.model = mujoco.MjModel.from_xml_path(str(self.spec.mjcf_path))
        self.data = mujoco.MjData(self.model)
        self._mj = mujoco
        self._qpos_adr: dict[str, int] = {}
        for j in range(self.model.njnt):
            name = mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_JOINT, j)
            if name:
                self._qpos_adr[name] = int(self.model.jnt_qposadr[j])
        self._site = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, self.spec.ee_site)
        body_of = self.model.geom_bodyid
        # the arm's geoms: those of bodies below the world (the table and the scene stay out)
        g = mujoco.mjtGeom
        drawn = {int(g.mjGEOM_CAPSULE), int(g.mjGEOM_BOX), int(g.mjGEOM_SPHERE), int(g.mjGEOM_CYLINDER)}
        self._geoms = [i for i in range(self.model.ngeom) if body_of[i] > 0 and self.model.geom_type[i] in drawn]
        self.ee_position = np.zeros(3)

    def pose(self, names: tuple[str, ...], position: np.ndarray) -> None:
        """Set the named joints (unknown names are ignored) and run forward kinematics."""
        for name, q in zip(names, position, strict=True):
            adr = self._qpos_adr.get(name)
            if adr is not None:
                self.data.qpos[adr] = q
        self._mj.mj_kinematics(self.model, self.data)
        if self._site >= 0:
            self.ee_position = self.data.site_xpos[self._site].copy()

    def archetypes(self) -> list[Any]:
        """Rerun archetypes of the posed geoms (one per geom type)."""
        import rerun as rr

        mj, m, d = self._mj, self.model, self.data
        caps: dict[str, list[Any]] = collections.defaultdict(list)
        boxes: dict[str, list[Any]] = collections.defaultdict(list)
        for g in self._geoms:
            rot = d.geom_xmat[g].reshape(3, 3)
            quat = np.empty(4)
            mj.mju_mat2Quat(quat, d.geom_xmat[g])
            xyzw = [quat[1], quat[2], quat[3], quat[0]]
            rgba = (np.clip(m.geom_rgba[g], 0, 1) * 255).astype(np.uint8)
            size, t = m.geom_size[g], int(m.geom_type[g])
            if t in (int(mj.mjtGeom.mjGEOM_CAPSULE), int(mj.mjtGeom.mjGEOM_CYLINDER), int(mj.mjtGeom.mjGEOM_SPHERE)):
                half = 0.0 if t == int(mj.mjtGeom.mjGEOM_SPHERE) else float(size[1])
                caps["t"].append(d.geom_xpos[g] - rot[:, 2] * half)  # Rerun's capsule starts at its translation
                caps["q"].append(xyzw)
                caps["len"].append(2 * half)
                caps["r"].append(float(size[0]))
                caps["c"].append(rgba)
            else:
                boxes["t"].append(d.geom_xpos[g].copy())
                boxes["q"].append(xyzw)
                boxes["h"].append(size[:3].copy())
                boxes["c"].append(rgba)
        out: list[Any] = []
        if caps:
            out.append(rr.Capsules3D(lengths=caps["len"], radii=caps["r"], translations=caps["t"],
                                     quaternions=caps["q"], colors=caps["c"], fill_mode="solid"))  # fmt: skip
        if boxes:
            out.append(rr.Boxes3D(half_sizes=boxes["h"], centers=boxes["t"], quaternions=boxes["q"],
                                  colors=boxes["c"], fill_mode="solid"))  # fmt: skip
        return out


def _robot_for(namespace: str, names: tuple[str, ...]) -> str | None:
    from uniros_async.robots import get_robot_spec, robot_names

    known = robot_names()
    if namespace in known:
        return namespace
    for name in known:
        try:
            spec = get_robot_spec(name)
        except Exception:  # a user's robot that does not load is not this view's concern
            continue
        if tuple(names[: spec.n_arm_joints]) == spec.arm_joint_names:
            return name
    return None


class SceneLogger:
    """Logs bus messages into a Rerun recording (see the module docstring).

    Args:
        recording: the ``rerun.RecordingStream`` to log into.
    """

    def __init__(self, recording: Any) -> None:
        self.rec = recording
        self.arms: dict[str, ArmGeoms | None] = {}
        self.trails: dict[str, collections.deque[np.ndarray]] = {}
        self.counts: collections.Counter[str] = collections.Counter()

    def _at(self, t_ns: int) -> None:
        self.rec.set_time("time", duration=t_ns / 1e9)

    def log(self, topic: str, msg: Any, t_ns: int) -> None:
        """Log ``msg`` of ``topic`` at ``t_ns``; a type the view does not draw is counted and left out."""
        if isinstance(msg, JointState):
            self._joint_state(topic, msg, t_ns)
        elif isinstance(msg, JointCommand):
            self._command(topic, msg, t_ns)
        elif isinstance(msg, Marker):
            self._marker(topic, msg, t_ns)
        elif isinstance(msg, Image):
            self._image(topic, msg, t_ns)
        else:
            self.counts["not drawn"] += 1
            return
        self.counts[topic] += 1

    @staticmethod
    def _ns(topic: str) -> str:
        parts = topic.strip("/").split("/")
        return "/".join(parts[:-1]) or parts[0]

    def _joint_state(self, topic: str, msg: JointState, t_ns: int) -> None:
        import rerun as rr

        ns = self._ns(topic)
        if ns not in self.arms:
            robot = _robot_for(ns.rsplit("/", 1)[-1], msg.name)
            self.arms[ns] = ArmGeoms(robot) if robot is not None else None
            if robot is None:
                logger.warning("%s: no registered robot has the joints %s; its curves only", topic, msg.name)
            self._layout(msg.name)
        self._at(t_ns)
        for name, q in zip(msg.name, msg.position, strict=True):
            self.rec.log(f"joints/{ns}/{name}/measured", rr.Scalars(float(q)))
        arm = self.arms[ns]
        if arm is None:
            return
        arm.pose(msg.name, msg.position)
        self.rec.log(f"arms/{ns}/links", *arm.archetypes())
        trail = self.trails.setdefault(ns, collections.deque(maxlen=TRAIL_LENGTH))
        trail.append(arm.ee_position)
        self.rec.log(f"arms/{ns}/ee_trail", rr.LineStrips3D([np.array(trail)], colors=[[40, 200, 40]], radii=0.003))

    def _layout(self, joints: tuple[str, ...]) -> None:
        """The viewer's layout: the 3D scene and the cameras on the left, a plot per joint of each arm (commanded
        beside measured) on the right."""
        import rerun.blueprint as rrb

        EYE = rrb.EyeControls3D(position=ARM_EYE[0], look_target=ARM_EYE[1], eye_up=(0.0, 0.0, 1.0))

        plots = [
            rrb.TimeSeriesView(origin=f"joints/{ns}/{j}", name=f"{ns} {j}")
            for ns, arm in self.arms.items()
            for j in (arm.spec.arm_joint_names if arm is not None else joints)
        ]
        scene = rrb.Spatial3DView(origin="/", contents=["arms/**", "markers/**"], name="arms", eye_controls=EYE)
        left = rrb.Vertical(scene, rrb.Spatial2DView(origin="cameras", name="cameras"), row_shares=[3, 1])
        self.rec.send_blueprint(rrb.Blueprint(rrb.Horizontal(left, rrb.Grid(*plots), column_shares=[3, 2]),
                                              collapse_panels=True))  # fmt: skip

    def _command(self, topic: str, msg: JointCommand, t_ns: int) -> None:
        import rerun as rr

        ns = self._ns(topic)
        arm = self.arms.get(ns)
        robot = None if arm is not None else _robot_for(ns.rsplit("/", 1)[-1], ())
        if arm is not None:
            names = arm.spec.arm_joint_names
        elif robot is not None:
            from uniros_async.robots import get_robot_spec

            names = get_robot_spec(robot).arm_joint_names
        else:
            names = tuple(f"joint{i}" for i in range(msg.position.size))
        self._at(t_ns)
        for name, q in zip(names, msg.position, strict=False):
            self.rec.log(f"joints/{ns}/{name}/commanded", rr.Scalars(float(q)))

    def _marker(self, topic: str, msg: Marker, t_ns: int) -> None:
        import rerun as rr

        path = f"markers/{topic.strip('/')}/{msg.ns or 'default'}/{msg.id}"
        stamp = msg.header.stamp_ns if msg.header.stamp_ns > 0 else t_ns
        self._at(stamp)
        if msg.action == "delete":
            self.rec.log(path, rr.Clear(recursive=False))
            return
        rgba = (np.clip(msg.color, 0, 1) * 255).astype(np.uint8)
        label = msg.text or None
        pos, scale = msg.position, msg.scale
        if msg.kind == "line_strip" and msg.points is not None:
            arch: Any = rr.LineStrips3D([msg.points], colors=[rgba], radii=float(scale[0]) / 2, labels=label)
        elif msg.kind == "points" and msg.points is not None:
            arch = rr.Points3D(msg.points, colors=[rgba], radii=float(scale[0]) / 2, labels=label)
        elif msg.kind == "cube":
            arch = rr.Boxes3D(half_sizes=[scale / 2], centers=[pos], colors=[rgba], labels=label)
        elif msg.kind == "text":
            arch = rr.Points3D([pos], colors=[rgba], radii=0.002, labels=msg.text, show_labels=True)
        elif msg.kind == "arrow":
            arch = rr.Arrows3D(origins=[pos], vectors=[scale], colors=[rgba], labels=label)
        elif msg.kind == "cylinder":
            arch = rr.Cylinders3D(lengths=[scale[2]], radii=[scale[0] / 2], centers=[pos], colors=[rgba],
                                  labels=label, fill_mode="solid")  # fmt: skip
        else:
            arch = rr.Points3D([pos], colors=[rgba], radii=float(scale[0]) / 2, labels=label)
        self.rec.log(path, arch)
        if msg.lifetime_s > 0:
            self._at(stamp + int(msg.lifetime_s * 1e9))  # Rerun takes data at any time: the removal is logged now
            self.rec.log(path, rr.Clear(recursive=False))

    def _image(self, topic: str, msg: Image, t_ns: int) -> None:
        import rerun as rr

        self._at(msg.header.stamp_ns if msg.header.stamp_ns > 0 else t_ns)
        channels = msg.data.shape[2]
        if channels in (3, 4):
            image = rr.Image(msg.data, color_model="RGB" if channels == 3 else "RGBA")
        else:
            image = rr.Image(msg.data[:, :, 0], color_model="L")
        self.rec.log(f"cameras/{topic.strip('/')}", image)
