"""Pictures of an arm: offscreen PNGs (headless) and the interactive MuJoCo viewer (where a display exists).

Offscreen GL on a headless Linux machine needs EGL (Mesa's software device works without a GPU) or OSMesa.
MuJoCo picks its GL backend once, from ``MUJOCO_GL``, when ``mujoco`` is first imported, which in a uniros
process happens long before anything renders. So this module creates the GL context itself, with the first
backend that works: ``$MUJOCO_GL`` if set, then ``egl``, then ``osmesa``, then ``glfw`` (only with a display),
and renders with MuJoCo's own calls (what ``mujoco.Renderer`` does inside), adding the goal and EE markers to
the scene with ``mjv_initGeom`` after ``mjv_updateScene``.

Debian packages: EGL: ``libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1``; OSMesa: ``libosmesa6``.
"""

from __future__ import annotations

import ctypes.util
import logging
import os
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from uniros_async.errors import ConfigError, RenderError
from uniros_async.robots import RobotSpec, get_robot_spec

__all__ = ["RenderError", "gl_backend", "render_png", "render_rgb", "view", "write_png"]

logger = logging.getLogger(__name__)

GOAL_RGBA = (0.9, 0.1, 0.1, 0.9)
EE_RGBA = (0.1, 0.8, 0.1, 0.9)


_BACKEND: tuple[str, Any] | None = None


def _has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _try_backend(name: str) -> Any:
    platform = os.environ.get("PYOPENGL_PLATFORM", "")
    if name == "egl":
        if ctypes.util.find_library("EGL") is None:
            raise RenderError("libEGL not found (apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1)")
        if platform not in ("", "egl"):
            raise RenderError(f"PYOPENGL_PLATFORM={platform!r} is set; EGL needs it unset or 'egl'")
        from mujoco.egl import GLContext
    elif name == "osmesa":
        if ctypes.util.find_library("OSMesa") is None:
            raise RenderError("libOSMesa not found (apt-get install libosmesa6)")
        if platform not in ("", "osmesa"):
            raise RenderError(f"PYOPENGL_PLATFORM={platform!r} is set; OSMesa needs it unset or 'osmesa'")
        from mujoco.osmesa import GLContext
    elif name == "glfw":
        if not _has_display():
            raise RenderError("glfw needs a display (DISPLAY or WAYLAND_DISPLAY)")
        from mujoco.glfw import GLContext
    else:
        raise RenderError(f"unknown GL backend {name!r}; expected egl, osmesa or glfw")
    ctx = GLContext(16, 16)  # prove it works before we rely on it
    ctx.free()
    return GLContext


def gl_backend() -> tuple[str, Any]:
    """The GL backend used for offscreen rendering in this process: ``(name, GLContext class)``.

    Raises:
        RenderError: none works; the message has each backend's reason.
    """
    global _BACKEND
    if _BACKEND is not None:
        return _BACKEND
    wanted = os.environ.get("MUJOCO_GL", "").lower().strip()
    order = [wanted] if wanted in ("egl", "osmesa", "glfw") else []
    order += [b for b in ("egl", "osmesa", "glfw") if b not in order]
    errors = []
    for name in order:
        try:
            _BACKEND = (name, _try_backend(name))
            logger.debug("offscreen rendering with %s", name)
            return _BACKEND
        except Exception as exc:  # noqa: BLE001 - every backend fails differently (ImportError, GLError, ...)
            errors.append(f"{name}: {type(exc).__name__}: {exc}")
    raise RenderError("no GL backend can render offscreen here; tried " + "; ".join(errors))


def _add_sphere(scene: Any, pos: ArrayLike, radius: float, rgba: Sequence[float]) -> None:
    import mujoco

    if scene.ngeom >= scene.maxgeom:
        raise RenderError(f"the scene is full ({scene.maxgeom} geoms)")
    mujoco.mjv_initGeom(
        scene.geoms[scene.ngeom],
        int(mujoco.mjtGeom.mjGEOM_SPHERE),
        np.array([radius, 0.0, 0.0]),
        np.asarray(pos, dtype=np.float64),
        np.eye(3).ravel(),
        np.asarray(rgba, dtype=np.float32),
    )
    scene.ngeom += 1


def _draw_legend(mjr: Any, entries: Sequence[tuple[str, Sequence[float]]], height: int) -> None:
    """One line per marker in the top left corner, each in its marker's colour."""
    import mujoco

    line = 28 / height  # the 150 % font is about 20 pixels high
    for k, (label, rgba) in enumerate(entries):
        r, g, b = (float(c) for c in rgba[:3])
        mujoco.mjr_text(int(mujoco.mjtFont.mjFONT_NORMAL), f"* {label}", mjr, 0.02, 1.0 - line * (k + 1), r, g, b)


def render_rgb(
    robot: RobotSpec | str,
    q: ArrayLike | None = None,
    goal: ArrayLike | None = None,
    *,
    width: int = 640,
    height: int = 480,
    camera: str | None = "overview",
    show_ee: bool = True,
    legend: bool = True,
    model: Any = None,
    data: Any = None,
) -> np.ndarray:
    """Render the arm at ``q`` (default: home) with an optional goal marker; returns (height, width, 3) uint8.

    Args:
        robot: a RobotSpec or robot name.
        q: arm joint positions; default ``RobotSpec.home_q_rad``. Ignored when ``data`` is given.
        goal: goal marker position (m, world), drawn as a red sphere.
        width: image width in pixels.
        height: image height in pixels.
        camera: a camera of the MJCF, or None for a free camera looking at the arm.
        show_ee: draw a green sphere at the EE site.
        legend: write in the top left corner, in their colours, what the markers drawn are ("end effector",
            "goal"), so a picture read alone says which sphere is which.
        model: an MjModel to draw (e.g. a running ServoSim's ``model``); default: load the robot's MJCF.
        data: an MjData of ``model`` to draw as it is (e.g. ``ServoSim.data``).

    Raises:
        ConfigError: bad ``q``, ``goal`` or size.
        RenderError: no GL backend works here.
    """
    import mujoco

    spec = get_robot_spec(robot) if isinstance(robot, str) else robot
    if not (16 <= width <= 8192 and 16 <= height <= 8192):
        raise ConfigError(f"render size: expected 16..8192 pixels each way, got {width}x{height}")
    if model is None:
        model = mujoco.MjModel.from_xml_path(str(spec.mjcf_path))
    if data is None:
        data = mujoco.MjData(model)
        key = next((k for k in range(model.nkey) if model.key(k).name == "home"), None)
        if key is not None:
            mujoco.mj_resetDataKeyframe(model, data, key)
        qa = np.asarray(spec.home_q_rad if q is None else q, dtype=np.float64)
        if qa.shape != (spec.n_arm_joints,) or not np.isfinite(qa).all():
            raise ConfigError(f"q: expected {spec.n_arm_joints} finite joint positions, got {list(qa)}")
        for name, value in zip(spec.arm_joint_names, qa, strict=True):
            data.qpos[model.jnt_qposadr[model.joint(name).id]] = value
        mujoco.mj_forward(model, data)
    goal_arr = None
    if goal is not None:
        goal_arr = np.asarray(goal, dtype=np.float64)
        if goal_arr.shape != (3,) or not np.isfinite(goal_arr).all():
            raise ConfigError(f"goal: expected 3 finite coordinates, got {goal!r}")

    _, gl_context_cls = gl_backend()
    # the offscreen buffer must be at least the image size
    model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
    model.vis.global_.offheight = max(model.vis.global_.offheight, height)
    ctx = gl_context_cls(width, height)
    ctx.make_current()
    mjr = None
    try:
        mjr = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, mjr)
        scene = mujoco.MjvScene(model, maxgeom=1000)
        cam = mujoco.MjvCamera()
        cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera) if camera else -1
        if cam_id >= 0:
            cam.type, cam.fixedcamid = mujoco.mjtCamera.mjCAMERA_FIXED, cam_id
        else:
            mujoco.mjv_defaultFreeCamera(model, cam)
        opt = mujoco.MjvOption()
        mujoco.mjv_updateScene(model, data, opt, None, cam, mujoco.mjtCatBit.mjCAT_ALL, scene)
        if goal_arr is not None:
            _add_sphere(scene, goal_arr, 0.02, GOAL_RGBA)
        site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, spec.ee_site) if show_ee else -1
        if site >= 0:
            _add_sphere(scene, data.site_xpos[site], 0.016, EE_RGBA)
        markers = [("end effector", EE_RGBA, site >= 0), ("goal", GOAL_RGBA, goal_arr is not None)]
        viewport = mujoco.MjrRect(0, 0, width, height)
        mujoco.mjr_render(viewport, scene, mjr)
        if legend:
            _draw_legend(mjr, [(label, rgba) for label, rgba, drawn in markers if drawn], height)
        rgb = np.empty((height, width, 3), dtype=np.uint8)
        mujoco.mjr_readPixels(rgb, None, viewport, mjr)
        return np.flipud(rgb).copy()
    finally:
        if mjr is not None:
            mjr.free()
        ctx.free()


def write_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write an (h, w, 3) uint8 image as PNG (zlib only, no imaging library needed)."""
    img = np.ascontiguousarray(rgb, dtype=np.uint8)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ConfigError(f"write_png: expected an (h, w, 3) image, got shape {img.shape}")
    h, w, _ = img.shape
    raw = b"".join(b"\x00" + img[y].tobytes() for y in range(h))

    def chunk(tag: bytes, body: bytes) -> bytes:
        return len(body).to_bytes(4, "big") + tag + body + zlib.crc32(tag + body).to_bytes(4, "big")

    ihdr = w.to_bytes(4, "big") + h.to_bytes(4, "big") + bytes([8, 2, 0, 0, 0])
    p = Path(path)
    png = chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + png)
    return p


def render_png(
    robot: RobotSpec | str,
    q: ArrayLike | None = None,
    goal: ArrayLike | None = None,
    out: str | Path = "pic.png",
    width: int = 640,
    height: int = 480,
    **kwargs: Any,
) -> Path:
    """Render the arm (see ``render_rgb`` for the arguments) and write it to ``out`` as PNG.

    Returns:
        The path written.

    Raises:
        ConfigError: bad arguments.
        RenderError: no GL backend works here.
    """
    return write_png(out, render_rgb(robot, q, goal, width=width, height=height, **kwargs))


def view(robot: RobotSpec | str) -> None:
    """Open MuJoCo's interactive viewer on the arm at home (blocks until the window closes).

    Raises:
        RenderError: there is no display (use ``render_png`` / ``uniros robot render`` instead).
    """
    if not _has_display():
        raise RenderError(
            "the interactive viewer needs a display (DISPLAY or WAYLAND_DISPLAY is unset); on a headless machine "
            "use `uniros robot render ROBOT --out pic.png`"
        )
    import mujoco
    import mujoco.viewer

    from uniros_async.sim.servo import ServoSim

    sim = ServoSim(robot)
    mujoco.viewer.launch(sim.model, sim.data)
