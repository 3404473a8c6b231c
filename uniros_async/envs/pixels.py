"""Pixel observations: an env's camera frames in its observation (``obs_mode="pixels"`` or ``"pixels+state"``).

With pixels the observation is a Dict: ``pixels``, the newest frame of the env's camera as uint8
(height, width, 3) at ``image_size``, and with ``pixels+state`` also ``state``, the task's vector. ``info`` gets
``frame_age_s`` (how old the frame is at the tick that built the observation) and ``frame_stale`` (older than
``camera_timeout_s``: the camera stopped, or never started). A stale frame is still handed over (the agent decides);
``reset`` waits for a fresh frame and raises RobotError naming the topic when none comes.

The frames come from the camera topic ``/<arm>/<camera>/color/image_raw``. On a sim placement (``robot="sim"``,
``"sim-process"``, ``"emulated-real"``) the env runs the arm's sim cameras itself (camera/sim.py) at ``image_size``:
on a sim clock on its own loop, in sim time; on a wall clock in a render process of its own
(camera/render_process.py), so that no render holds the GIL the env loop needs. The frame in the observation is the
published array itself, never copied again. A frame of another size or encoding (a real camera's ``bgr8`` or
``mono8``) is converted to RGB and resized by nearest neighbour; a frame the observation cannot hold gives a black
frame with ``frame_stale`` set in its place (and a warning naming it, once).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np

from uniros_async.bus.messages import Image, Marker
from uniros_async.bus.qos import latest
from uniros_async.camera.topic import camera_topic, frame_age_ns
from uniros_async.errors import RobotError
from uniros_async.sim_clock import SimClock

if TYPE_CHECKING:
    from uniros_async.camera.sim import SimCameraNode
    from uniros_async.envs.config import EnvConfig

__all__ = ["CAMERA_TICK_GAP_NS", "OBS_MODES", "SIM_CAMERA_PLACEMENTS", "PixelSource", "pixel_space"]

logger = logging.getLogger(__name__)

OBS_MODES = ("state", "pixels", "pixels+state")
SIM_CAMERA_PLACEMENTS = ("sim", "sim-process", "emulated-real")
"""Placements whose arm is simulated: the env renders its cameras (``sim_camera`` unset)."""
CAMERA_TICK_GAP_NS = 1_000_000
"""A sim camera the env runs ticks this long after the env loop's ticks on a wall clock, before them on a sim clock
(``PixelSource.camera_phase_ns``)."""
MJCF_CAMERAS = {"camera": "scene", "wrist_camera": "wrist"}
"""The MJCF camera behind each sim camera topic name."""


def pixel_space(obs_mode: str, image_size: tuple[int, int], state_space: gym.Space[Any]) -> gym.spaces.Dict:
    """The Dict observation space of ``obs_mode`` (``pixels`` or ``pixels+state``)."""
    h, w = image_size
    spaces: dict[str, gym.Space[Any]] = {"pixels": gym.spaces.Box(0, 255, (h, w, 3), np.uint8)}
    if obs_mode == "pixels+state":
        spaces["state"] = state_space
    return gym.spaces.Dict(spaces)


class PixelSource:
    """The camera frames of one env: the subscription, the sim cameras it runs, the observation's ``pixels``."""

    def __init__(self, config: EnvConfig, robot: Any) -> None:
        self.config = config
        self.robot = robot
        self.obs_mode: str = config.obs_mode
        self.image_size: tuple[int, int] = (int(config.image_size[0]), int(config.image_size[1]))
        self.topic = camera_topic(config.camera, f"/{robot.name}")
        placement_sim = config.robot in SIM_CAMERA_PLACEMENTS
        self.sim_camera: bool = placement_sim if config.sim_camera is None else bool(config.sim_camera)
        self.cameras: SimCameraNode | None = None
        self._sub: Any = None
        self._clock: Any = None
        self._index_cache: tuple[tuple[int, ...], tuple[np.ndarray, np.ndarray]] | None = None
        self._blank = np.zeros((*self.image_size, 3), np.uint8)
        self._warned = False

    def space(self, state_space: gym.Space[Any]) -> gym.spaces.Dict:
        """The observation space around the task's ``state_space``."""
        return pixel_space(self.obs_mode, self.image_size, state_space)

    def camera_rate_hz(self, env_loop_rate_hz: float) -> float:
        """The sim cameras' rate: ``camera_rate_hz``; unset, 30 Hz on a wall clock and the env loop's rate on a
        sim clock (a frame for every tick; more would only be rendered and dropped)."""
        if self.config.camera_rate_hz is not None:
            return float(self.config.camera_rate_hz)
        return env_loop_rate_hz if self.config.clock == "sim" else 30.0

    def camera_phase_ns(self, tick_phase_ns: int) -> int:
        """Where the sim camera ticks on the clock's grid, given where the env loop ticks (``tick_phase_ns``): on a
        wall clock just after the loop's ticks, so that a frame never renders, nor arrives, when a servo or env tick
        is due; on a sim clock just before them (time stands still while a frame renders), so that each tick
        observes a frame of its own instant's joint state."""
        if self.config.clock == "sim":
            return max(tick_phase_ns - CAMERA_TICK_GAP_NS, 0)
        return tick_phase_ns + CAMERA_TICK_GAP_NS

    async def join(
        self,
        node: Any,
        stack: contextlib.AsyncExitStack,
        domain: Any,
        transport: str,
        options: Any,
        clock: Any,
        rate_hz: float,
        phase_s: float = 0.0,
    ) -> None:
        """Subscribe to the camera topic on ``node`` and, for a sim arm, run its camera in ``stack``, ticking
        ``phase_s`` after its grid (``SimCameraConfig.phase_s``)."""
        self._clock = clock
        if self.sim_camera:
            from uniros_async.camera.sim import SimCameraConfig, open_sim_cameras

            name = self.config.camera
            h, w = self.image_size
            cam = SimCameraConfig(
                camera=MJCF_CAMERAS.get(name, name), name=name, width=w, height=h, rate_hz=rate_hz, phase_s=phase_s
            )
            self.cameras = await stack.enter_async_context(
                open_sim_cameras(  # on a wall clock in a process of its own: a render never holds this loop's GIL
                    self.robot,
                    domain=domain,
                    cameras=[cam],
                    clock=clock,
                    transport=transport,
                    options=options,
                    render="process",
                )
            )
        self._sub = await node.create_subscription(Image, self.topic, qos=latest())

    def stats(self) -> dict[str, Any] | None:
        """The sim camera's counters: ``frames`` published, ticks ``skipped`` (renderer busy), ``render_median_ms``;
        None without a sim camera."""
        if self.cameras is None:
            return None
        st = self.cameras.stats[0]
        median = float(np.median(st.render_ns)) / 1e6 if st.render_ns else float("nan")
        return {"frames": st.frames, "skipped": st.skipped, "render_median_ms": median}

    def show(self, marker: Marker) -> None:
        """Put ``marker`` in this env's sim camera's picture at once (the task also publishes it on ``markers_in``)."""
        if self.cameras is not None:
            self.cameras._on_marker(marker)

    def _age_ns(self, img: Image) -> int:
        same = self.cameras is not None  # stamped in this process, on the env's clock
        return frame_age_ns(img, self._sub.latest_recv_ns, self._clock.now_ns(), same_clock=same)

    def _rgb(self, img: Image) -> np.ndarray | None:
        """``img`` as uint8 RGB at ``image_size``: as it is when it already is, else converted (``bgr8``, ``mono8``)
        and resized by nearest neighbour; None for an encoding or shape it cannot be (logged once per topic)."""
        data, enc = img.data, img.encoding
        h, w = self.image_size
        if enc == "rgb8" and data.shape == (h, w, 3):
            return data
        channels = data.shape[2] if data.ndim == 3 else 0
        if (enc, channels) not in (("rgb8", 3), ("bgr8", 3), ("mono8", 1)):
            if not self._warned:
                self._warned = True
                logger.warning(
                    "%s: a %s frame of shape %s is not an image the observation can hold (rgb8, bgr8 or mono8, "
                    "height x width x channels); the frame is left out and ages",
                    self.topic,
                    enc,
                    data.shape,
                )
            return None
        cache = self._index_cache
        if cache is None or cache[0] != data.shape:
            rows = (np.arange(h) * data.shape[0] // h).astype(np.intp)
            cols = (np.arange(w) * data.shape[1] // w).astype(np.intp)
            cache = self._index_cache = (data.shape, (rows[:, None], cols[None, :]))
        rows_i, cols_i = cache[1]
        out: np.ndarray = data[rows_i, cols_i]
        if enc == "bgr8":
            out = out[..., ::-1]
        elif enc == "mono8":
            out = np.repeat(out, 3, axis=2)
        return np.ascontiguousarray(out)

    def observe(self, state_obs: Any, info: dict[str, Any]) -> dict[str, Any]:
        """The Dict observation of the newest frame and ``state_obs``; sets ``info["frame_age_s"]`` and
        ``info["frame_stale"]``."""
        img = self._sub.latest() if self._sub is not None else None
        frame = None if img is None else self._rgb(img)
        if img is None or frame is None:
            frame, age_s = self._blank, float("inf")
        else:
            age_s = self._age_ns(img) / 1e9
        info["frame_age_s"] = age_s
        info["frame_stale"] = not age_s <= self.config.camera_timeout_s
        obs: dict[str, Any] = {"pixels": frame}
        if self.obs_mode == "pixels+state":
            obs["state"] = state_obs
        return obs

    async def fresh(self, after_ns: int) -> None:
        """Make sure a frame stamped after ``after_ns`` has arrived: rendered now by a sim camera that renders in
        sim time, else waited for up to ``camera_timeout_s``.

        Raises:
            RobotError: no frame within ``camera_timeout_s`` (names the topic and the newest frame's age).
        """
        cams = self.cameras
        called_ns = time.monotonic_ns()
        if cams is not None and isinstance(self._clock, SimClock):
            cams.render_now(0)
        timeout_s = self.config.camera_timeout_s
        deadline = time.monotonic() + timeout_s
        while True:
            img = self._sub.latest()
            if img is not None:
                if cams is not None and img.header.stamp_ns >= after_ns:  # our own camera: stamped on our clock
                    return
                if cams is None and self._sub.latest_recv_ns >= called_ns:  # another's: arrived since the call
                    return
            if time.monotonic() > deadline:
                break
            await asyncio.sleep(0.005)
        img = self._sub.latest()
        newest = "none arrived" if img is None else f"the newest is {self._age_ns(img) / 1e9:.2f} s old"
        raise RobotError(
            f"{self.robot.name}: no camera frame on {self.topic} within camera_timeout_s={timeout_s} ({newest}); "
            "is the camera running?"
        )
