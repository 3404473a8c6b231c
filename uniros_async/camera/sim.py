"""Sim cameras: the MJCF cameras of a simulated arm, rendered offscreen and published as camera topics.

Each arm's MJCF has a scene camera (``scene``: beside the arm, looking down at the table in front of it) and a
wrist camera (``wrist``: on the gripper, looking ahead and down). ``open_sim_cameras`` runs a bus node that renders
them at their own rate and publishes each as ``Image`` on ``/<arm>/camera/color/image_raw`` (``scene``) and
``/<arm>/wrist_camera/color/image_raw`` (``wrist``), the names of a RealSense/UVC driver (camera/topic.py).

The node draws the arm as its ``joint_states`` say (its own copy of the model, posed by ``mj_kinematics``), so it
runs wherever the arm's domain reaches: in the env's process beside an in-process sim, or beside a sim in another
process. It also draws the markers it receives on ``markers_in`` (the goal a task shows: spheres and cylinders,
as the sim node gets them), so a target on the table is in the picture.

Where the rendering runs:

- on a wall clock, off the loop: a node timer at each camera's rate takes the newest joint state and hands the
  frame to the renderer, which hands the image back to the loop to publish; a frame not finished by the camera's
  next tick is skipped (``CameraStats.skipped``), never queued. The renderer is a thread of the node's process
  (``render="thread"``) or a child process (``render="process"``, camera/render_process.py). Mesa's software
  rasteriser holds the GIL of the process that reads the pixels while it draws, so loops that share the process
  wait for it in thread mode; in process mode they never do, which is what an env uses. In process mode the frame
  goes from the child's memfd straight into a loaned frame (``ImagePublisher.loan``): with one subscriber in
  another process over shm, that is the frame's place in its ring, and the frame's only copy after the render;
- on a SimClock, in the timer's callback on the loop: time stands still while the frame renders, so the frame
  shows the arm at its stamp exactly, and the sim's loops keep their sim-time schedule to the nanosecond.

Offscreen GL: EGL (Mesa's software device works without a GPU) or OSMesa; sim/render.py picks the backend, and
names the Debian packages to install when none works (``RenderError``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import queue
import threading
import time
from collections.abc import AsyncIterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from uniros_async.bus import open_node
from uniros_async.bus.messages import JointState, Marker
from uniros_async.bus.qos import latest, reliable
from uniros_async.bus.tasks import unwrap_task_group
from uniros_async.camera.topic import FrameSpec, ImagePublisher, camera_topic
from uniros_async.clock import Clock, grid_after
from uniros_async.errors import ConfigError, TransportClosedError
from uniros_async.robots import RobotSpec, get_robot_spec
from uniros_async.sim_clock import SimClock
from uniros_async.transports.base import TransportOptions

__all__ = ["CAMERA_TOPIC_NAMES", "CameraStats", "SimCameraConfig", "SimCameraNode", "SimRenderer", "open_sim_cameras"]

logger = logging.getLogger(__name__)

CAMERA_TOPIC_NAMES = {"scene": "camera", "wrist": "wrist_camera"}
"""The topic name (a RealSense/UVC driver's camera name) of each MJCF camera every arm has."""
RENDER_MODES = ("thread", "process")
"""Where a node on a wall clock renders: a thread of its own, or a child process (camera/render_process.py)."""
THREAD_JOIN_TIMEOUT_S = 5.0
"""Bound on waiting for the render thread to finish its frame and end when the node closes."""
LOAN_TIMEOUT_S = 1.0
"""How long a rendered frame waits for room in a subscriber's ring before it is skipped."""


@dataclass(frozen=True, kw_only=True)
class SimCameraConfig:
    """One sim camera: the MJCF ``camera``, its frame size and rate, and its topic's camera name.

    Raises:
        ConfigError: a rate that is not > 0 and <= 240 Hz, or a bad size (FrameSpec's checks).
    """

    camera: str = "scene"
    """The MJCF camera (every arm has ``scene`` and ``wrist``)."""
    width: int = 84
    height: int = 84
    rate_hz: float = 30.0
    name: str = ""
    """The topic's camera name (``<ns>/<name>/color/image_raw``); empty: ``CAMERA_TOPIC_NAMES`` or the MJCF name."""
    phase_s: float = 0.0
    """The camera ticks this long after the points of the clock's grid of its period. An env that runs its camera
    puts the renders just after its own loop's ticks, so that a frame never renders at the instant a servo or env
    tick is due (the 30 Hz grid holds every point of a 10 Hz loop's)."""

    def __post_init__(self) -> None:
        if not 0 <= self.phase_s < 1:
            raise ConfigError(f"camera {self.camera!r}: phase_s expected >= 0 and < 1, got {self.phase_s}")
        if not 0 < self.rate_hz <= 240:
            raise ConfigError(f"camera {self.camera!r}: rate_hz expected > 0 and <= 240, got {self.rate_hz}")
        FrameSpec(width=self.width, height=self.height)

    @property
    def topic_name(self) -> str:
        """The camera name of its topic."""
        return self.name or CAMERA_TOPIC_NAMES.get(self.camera, self.camera)


@dataclass
class CameraStats:
    """Counters of one sim camera: frames published, ticks skipped (the renderer still busy), render times (ns)."""

    frames: int = 0
    skipped: int = 0
    render_ns: list[int] = field(default_factory=list)


class SimRenderer:
    """Renders the cameras of one arm's model at given joint positions (use it in one thread only: the thread that
    first calls ``render`` owns its GL context).

    Args:
        robot: the arm.
        cameras: the cameras to render (MJCF names and sizes).

    Raises:
        ConfigError: a camera the arm's MJCF does not have (the ones it has are named).
    """

    def __init__(self, robot: RobotSpec, cameras: Sequence[SimCameraConfig]) -> None:
        import mujoco

        self.robot = robot
        self.model = mujoco.MjModel.from_xml_path(str(robot.mjcf_path))
        self.data = mujoco.MjData(self.model)
        names = [self.model.camera(i).name for i in range(self.model.ncam)]
        self.cam_ids = []
        for cfg in cameras:
            if cfg.camera not in names:
                raise ConfigError(f"{robot.name}: its MJCF has no camera {cfg.camera!r}; it has {names}")
            self.cam_ids.append(names.index(cfg.camera))
        self.sizes = [(c.width, c.height) for c in cameras]
        # the offscreen buffer just fits the largest camera: the software rasteriser clears and resolves all of it
        # for every frame, so a buffer larger than the frames (MuJoCo's default is 640x480) costs every frame
        self.model.vis.global_.offwidth = max(w for w, _ in self.sizes)
        self.model.vis.global_.offheight = max(h for _, h in self.sizes)
        self.model.vis.quality.offsamples = 0  # no multisampling: a learning frame needs no anti-aliasing
        self._qpos_adr = {self.model.joint(i).name: int(self.model.jnt_qposadr[i]) for i in range(self.model.njnt)}
        key = next((k for k in range(self.model.nkey) if self.model.key(k).name == "home"), None)
        if key is not None:
            mujoco.mj_resetDataKeyframe(self.model, self.data, key)
        self._bufs = [np.empty((h, w, 3), dtype=np.uint8) for w, h in self.sizes]
        self._ctx: Any = None
        self._mjr: Any = None
        self._scene: Any = None

    def _open_gl(self) -> None:
        import mujoco

        from uniros_async.sim.render import gl_backend

        _, gl_context_cls = gl_backend()
        w = int(self.model.vis.global_.offwidth)
        h = int(self.model.vis.global_.offheight)
        self._ctx = gl_context_cls(w, h)
        self._ctx.make_current()
        self._mjr = mujoco.MjrContext(self.model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._mjr)
        self._scene = mujoco.MjvScene(self.model, maxgeom=1000)
        # no shadow map: in Mesa's software rasteriser the 4096-pixel shadow pass costs far more than the frame
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        self._opt = mujoco.MjvOption()
        self._cams = []
        for cam_id in self.cam_ids:
            cam = mujoco.MjvCamera()
            cam.type, cam.fixedcamid = mujoco.mjtCamera.mjCAMERA_FIXED, cam_id
            self._cams.append(cam)

    def pose(self, names: Sequence[str], position: np.ndarray) -> None:
        """Set the named joints (a JointState's ``name`` and ``position``; unknown names are ignored)."""
        qpos, adr = self.data.qpos, self._qpos_adr
        for name, value in zip(names, position.tolist(), strict=True):
            i = adr.get(name)
            if i is not None:
                qpos[i] = value

    def render(self, index: int, markers: Sequence[Marker] = ()) -> np.ndarray:
        """Camera ``index``'s image of the arm as posed, with ``markers``: a new (height, width, 3) uint8 array.

        Raises:
            RenderError: no GL backend works here (the message names the Debian packages to install).
        """
        w, h = self.sizes[index]
        out = np.empty((h, w, 3), dtype=np.uint8)
        self.render_into(index, markers, out)
        return out

    def render_into(self, index: int, markers: Sequence[Marker], out: np.ndarray) -> None:
        """``render``, written into ``out`` (height, width, 3) uint8: the one copy out of GL's buffer, flipped from
        GL's bottom-up rows.

        Raises:
            RenderError: no GL backend works here (the message names the Debian packages to install).
        """
        import mujoco

        if self._ctx is None:
            self._open_gl()
        else:
            self._ctx.make_current()  # another renderer in this thread may have made its own context current
        model, data, scene = self.model, self.data, self._scene
        mujoco.mj_kinematics(model, data)
        mujoco.mj_camlight(model, data)  # the cameras' and lights' poses (mj_kinematics leaves them)
        mujoco.mjv_updateScene(model, data, self._opt, None, self._cams[index], mujoco.mjtCatBit.mjCAT_ALL, scene)
        for m in markers:
            _add_marker(scene, m)
        w, h = self.sizes[index]
        viewport = mujoco.MjrRect(0, 0, w, h)
        mujoco.mjr_render(viewport, scene, self._mjr)
        buf = self._bufs[index]
        mujoco.mjr_readPixels(buf, None, viewport, self._mjr)
        np.copyto(out, np.flipud(buf))  # GL's rows run bottom up

    def close(self) -> None:
        """Free the GL context (from the thread that rendered); idempotent."""
        if self._mjr is not None:
            self._mjr.free()
            self._mjr = None
        if self._ctx is not None:
            self._ctx.free()
            self._ctx = None


def _add_marker(scene: Any, m: Marker) -> None:
    import mujoco

    if m.action != "add" or scene.ngeom >= scene.maxgeom:
        return
    kinds = {"sphere": mujoco.mjtGeom.mjGEOM_SPHERE, "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER}
    kind = kinds.get(m.kind)
    if kind is None:
        return
    half = np.asarray(m.scale, dtype=np.float64) / 2  # a Marker's scale is its full size, as visualization_msgs'
    mujoco.mjv_initGeom(
        scene.geoms[scene.ngeom],
        int(kind),
        np.array([half[0], half[0], half[2]]),
        np.asarray(m.position, dtype=np.float64),
        np.eye(3).ravel(),
        np.asarray(m.color, dtype=np.float32),
    )
    scene.ngeom += 1


class SimCameraNode:
    """The bus node of an arm's sim cameras. Create with ``async with open_sim_cameras(robot, domain=...)``.

    Attributes:
        node: the bus node.
        cameras: the cameras' configs.
        publishers: one ImagePublisher per camera.
        stats: one CameraStats per camera.
    """

    def __init__(
        self, node: Any, robot: RobotSpec, cameras: Sequence[SimCameraConfig], namespace: str, render: str = "thread"
    ) -> None:
        if not cameras:
            raise ConfigError("sim cameras: expected at least one camera")
        if render not in RENDER_MODES:
            raise ConfigError(f"sim cameras: render expected one of {RENDER_MODES}, got {render!r}")
        self.node = node
        self.robot = robot
        self.namespace = namespace
        self.cameras = tuple(cameras)
        self.renderer = SimRenderer(robot, cameras)
        self.stats = [CameraStats() for _ in cameras]
        self.publishers: list[ImagePublisher] = []
        self._markers: dict[tuple[str, int], Marker] = {}
        self._busy = [False] * len(cameras)
        self._inline = isinstance(node.clock, SimClock)
        self.render_mode = "loop" if self._inline else render
        self._process: Any = None  # a RenderProcess with render="process"
        self._tg: asyncio.TaskGroup | None = None  # owns the tasks that publish the render process's frames
        self._stamps = [0] * len(cameras)
        self._requests: queue.SimpleQueue[tuple[int, JointState, tuple[Marker, ...], int] | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._failed: asyncio.Future[None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._watch_task: asyncio.Task[None] | None = None
        self._timers: list[Any] = []
        self._inline_stopped = False

    def topic(self, index: int = 0) -> str:
        """The absolute topic of camera ``index``."""
        return self.publishers[index].topic

    async def _start(self, tg: asyncio.TaskGroup) -> None:
        from uniros_async.sim.render import gl_backend

        if self.render_mode != "process":
            gl_backend()  # RenderError now, naming the packages to install, rather than in the render thread
        node = self.node
        self._loop = asyncio.get_running_loop()
        self._failed = self._loop.create_future()
        self._js = await node.create_subscription(JointState, "joint_states", qos=latest())
        await node.create_subscription(Marker, "markers_in", self._on_marker, qos=reliable(100))
        for cfg in self.cameras:
            spec = FrameSpec(width=cfg.width, height=cfg.height)
            topic = camera_topic(cfg.topic_name, self.namespace)
            self.publishers.append(await ImagePublisher.create(node, topic, spec, frame_id=cfg.topic_name))
        if self.render_mode == "thread":
            self._thread = threading.Thread(target=self._render_thread, name=f"{self.robot.name} cameras", daemon=True)
            self._thread.start()
        elif self.render_mode == "process":
            from uniros_async.camera.render_process import RenderProcess

            self._tg = tg
            self._process = RenderProcess(self.robot, self.cameras, self._on_process_frame, view=True)
            await self._process.start()
            self._failed = self._process.failed
        self._watch_task = tg.create_task(self._watch(), name="camera render thread watch")
        for i, cfg in enumerate(self.cameras):
            period_ns = round(1e9 / cfg.rate_hz)
            start = grid_after(node.now_ns(), period_ns, round(cfg.phase_s * 1e9) % period_ns)
            self._timers.append(node.create_timer(period_ns / 1e9, lambda i=i: self._on_tick(i), start_ns=start))

    def stop(self) -> None:
        """Stop rendering and publishing (a camera that stops: its subscribers' frames only age)."""
        for timer in self._timers:
            timer.cancel()
        self._inline_stopped = True

    async def _watch(self) -> None:
        assert self._failed is not None
        await self._failed  # raises what stopped the render thread

    def _on_marker(self, m: Marker) -> None:
        key = (m.ns, m.id)
        if m.action == "delete":
            self._markers.pop(key, None)
        else:
            self._markers[key] = m

    def _on_tick(self, index: int) -> None:
        js = self._js.latest()
        if js is None:
            return
        stamp = self.node.now_ns()
        markers = tuple(self._markers.values())
        if self._inline:
            t0 = time.perf_counter_ns()
            self.renderer.pose(js.name, js.position)
            frame = self.renderer.render(index, markers)
            self.stats[index].render_ns.append(time.perf_counter_ns() - t0)
            self._publish(index, frame, stamp)
            return
        if self._busy[index]:
            self.stats[index].skipped += 1
            return
        self._busy[index] = True
        if self._process is not None:
            self._stamps[index] = stamp
            self._process.request(index, js.name, js.position, markers)
            return
        self._requests.put((index, js, markers, stamp))

    def _on_process_frame(self, index: int, view: np.ndarray, render_ns: int) -> None:
        self.stats[index].render_ns.append(render_ns)
        assert self._tg is not None
        self._tg.create_task(self._publish_loaned(index, view, self._stamps[index]), name="camera frame")

    async def _publish_loaned(self, index: int, view: np.ndarray, stamp_ns: int) -> None:
        """Copy the render process's frame (its memfd, untouched until this camera's next request) into a loaned
        frame: with one remote subscriber over shm, the frame's one copy after the render."""
        try:
            async with asyncio.timeout(LOAN_TIMEOUT_S):
                async with self.publishers[index].loan(stamp_ns) as out:
                    np.copyto(out, view)
            self.stats[index].frames += 1
        except TimeoutError:  # a subscriber's ring stayed full: this frame is skipped, as a busy renderer's tick
            self.stats[index].skipped += 1
        except TransportClosedError:  # the node is closing
            pass
        finally:
            self._busy[index] = False

    def render_now(self, index: int) -> None:
        """Render camera ``index`` now, on the loop, and publish it (a node that renders in sim time; on a wall
        clock the next tick's frame comes from the render thread, and this does nothing)."""
        if self._inline and not self._inline_stopped:
            self._on_tick(index)

    def _publish(self, index: int, frame: np.ndarray, stamp_ns: int) -> None:
        self._busy[index] = False
        self.stats[index].frames += 1
        self.publishers[index].publish(frame, stamp_ns)

    def _render_thread(self) -> None:
        loop, failed = self._loop, self._failed
        assert loop is not None and failed is not None
        try:
            while True:
                req = self._requests.get()
                if req is None:
                    return
                index, js, markers, stamp = req
                t0 = time.perf_counter_ns()
                self.renderer.pose(js.name, js.position)
                frame = self.renderer.render(index, markers)
                self.stats[index].render_ns.append(time.perf_counter_ns() - t0)
                with contextlib.suppress(RuntimeError):  # the loop closed: the node is gone
                    loop.call_soon_threadsafe(self._publish, index, frame, stamp)
        except BaseException as exc:  # noqa: BLE001 - handed to the loop, which raises it in the node's task group
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(_fail, failed, exc)
        finally:
            self.renderer.close()

    async def _shutdown(self) -> None:
        self.stop()
        if self._process is not None:
            await self._process.aclose()
        thread = self._thread
        if thread is not None:
            self._requests.put(None)
            await asyncio.to_thread(thread.join, THREAD_JOIN_TIMEOUT_S)
            if thread.is_alive():
                logger.warning(
                    "%s cameras: the render thread did not end within %s s", self.robot.name, THREAD_JOIN_TIMEOUT_S
                )
        else:
            self.renderer.close()


def _fail(future: asyncio.Future[None], exc: BaseException) -> None:
    if not future.done():
        future.set_exception(exc)


@contextlib.asynccontextmanager
async def open_sim_cameras(
    robot: RobotSpec | str,
    *,
    domain: Any = None,
    namespace: str | None = None,
    cameras: Sequence[SimCameraConfig] | None = None,
    clock: Clock | None = None,
    node_name: str = "sim_cameras",
    transport: str = "auto",
    options: TransportOptions | None = None,
    render: str = "thread",
) -> AsyncIterator[SimCameraNode]:
    """Run the sim cameras of ``robot`` as a bus node for the duration of the block.

    Args:
        robot: a RobotSpec or robot name.
        domain: the Domain (or its URI) of the arm; None: ``$UNIROS_DOMAIN``.
        namespace: the arm's namespace; default ``/<robot name>``.
        cameras: the cameras; default the scene and wrist cameras at 84x84 and 30 Hz.
        clock: the domain's clock (a SimClock: frames render in sim time, on the loop).
        node_name: the node's name in the namespace.
        transport: the node's transport choice (``auto``, ``memory``, ``shm``, ``tcp``).
        options: transport options.
        render: on a wall clock, render in a ``"thread"`` of this process or in a child ``"process"``
            (camera/render_process.py: the GIL this process's loops need is never held by a render); on a SimClock
            frames render on the loop, in sim time, either way.

    Yields:
        The running SimCameraNode; leaving the block stops its timers and its render thread or process.

    Raises:
        ConfigError: an unknown robot or camera, a bad size or rate.
        RenderError: no offscreen GL here (the message names the Debian packages to install).
    """
    spec = get_robot_spec(robot) if isinstance(robot, str) else robot
    cams = tuple(cameras) if cameras is not None else (SimCameraConfig(camera="scene"), SimCameraConfig(camera="wrist"))
    ns = namespace if namespace is not None else f"/{spec.name}"
    async with open_node(
        node_name, domain=domain, namespace=ns, clock=clock, transport=transport, options=options
    ) as node:
        cam_node = SimCameraNode(node, spec, cams, ns, render)
        try:
            async with unwrap_task_group() as tg:
                await cam_node._start(tg)
                try:
                    yield cam_node
                finally:
                    if cam_node._watch_task is not None:
                        cam_node._watch_task.cancel()
        finally:
            await cam_node._shutdown()
