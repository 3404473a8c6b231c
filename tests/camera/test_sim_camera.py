"""Sim cameras: real offscreen rendering (EGL, Mesa's software device) of the arms' MJCF cameras onto camera topics."""

from __future__ import annotations

import asyncio
import os

import numpy as np
import pytest

from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import Header, Image, Marker
from uniros_async.camera import FrameError, FrameSpec, ImagePublisher, SimCameraConfig, camera_topic, open_sim_cameras
from uniros_async.errors import ConfigError
from uniros_async.sim.node import open_servo_sim
from uniros_async.sim.render import RenderError, _try_backend
from uniros_async.sim_clock import SimClock


def _red(img: np.ndarray) -> int:
    """Pixels that are clearly red (the target's colour; nothing else in the scene is)."""
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return int(((r > 150) & (g < 80) & (b < 80)).sum())


@pytest.mark.parametrize("arm", ["rx200", "ned2"])
async def test_scene_and_wrist_cameras_publish_on_driver_topics(arm: str) -> None:
    cams = [SimCameraConfig(camera="scene", width=96, height=64), SimCameraConfig(camera="wrist", rate_hz=15)]
    async with (
        open_domain() as domain,
        open_servo_sim(arm, domain=domain),
        open_sim_cameras(arm, domain=domain, cameras=cams) as node,
        open_node("viewer", domain=domain) as viewer,
    ):
        assert [node.topic(0), node.topic(1)] == [
            f"/{arm}/camera/color/image_raw",
            f"/{arm}/wrist_camera/color/image_raw",
        ]
        scene = await viewer.create_subscription(Image, node.topic(0))
        wrist = await viewer.create_subscription(Image, node.topic(1))
        async with asyncio.timeout(10):
            first = await scene.receive()
            w = await wrist.receive()
            second = await scene.receive()
        assert first.data.shape == (64, 96, 3) and first.data.dtype == np.uint8 and first.encoding == "rgb8"
        assert w.data.shape == (84, 84, 3) and w.header.frame_id == "wrist_camera"
        assert first.header.frame_id == "camera" and second.header.seq > first.header.seq
        assert 0 < second.header.stamp_ns - first.header.stamp_ns < 1e9  # 30 Hz, a skipped tick or two at most
        assert first.data.std() > 10  # a picture (arm on a table), not a blank buffer
        age_s = (viewer.now_ns() - second.header.stamp_ns) / 1e9
        assert 0 <= age_s < 1.0


async def test_a_target_marker_appears_in_the_scene_camera() -> None:
    cams = [SimCameraConfig(camera="scene", width=84, height=84)]
    clock = SimClock(time_scale=None)
    async with (
        open_domain() as domain,
        open_servo_sim("rx200", domain=domain, clock=clock),
        open_sim_cameras("rx200", domain=domain, cameras=cams, clock=clock) as node,
        open_node("task", domain=domain, namespace="/rx200", clock=clock) as task,
    ):
        sub = await task.create_subscription(Image, node.topic(0))
        markers = await task.create_publisher(Marker, "markers_in")
        async with asyncio.timeout(10):
            before = (await sub.receive()).data
            assert _red(before) == 0
            target = Marker(
                header=Header(frame_id="world"),
                ns="goal",
                kind="cylinder",
                position=np.array([0.22, -0.08, 0.002]),
                scale=np.array([0.05, 0.05, 0.004]),
                color=np.array([0.9, 0.05, 0.05, 1.0]),
            )
            markers.publish(target)
            while True:
                img = await sub.receive()
                if img.header.stamp_ns > clock.now_ns() - 1 and _red(img.data) > 0:
                    break
        ys, xs = np.nonzero(_red_mask(img.data))
        # the scene camera looks at (0.2, 0, 0) from y = +0.6 (image right = world -x, up = away from it): a target at
        # x > 0.2 is left of the centre, at y < 0 above it
        assert xs.mean() < 42 and ys.mean() < 42
        assert node.stats[0].render_ns  # rendered on the loop, in sim time


def _red_mask(img: np.ndarray) -> np.ndarray:
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (r > 150) & (g < 80) & (b < 80)


async def test_a_frame_of_another_size_or_encoding_is_refused_and_nothing_is_published() -> None:
    async with open_domain() as domain, open_node("cam", domain=domain) as node:
        pub = await ImagePublisher.create(node, camera_topic("camera", "/rx200"), FrameSpec(width=84, height=84))
        sub = await node.create_subscription(Image, "/rx200/camera/color/image_raw")
        with pytest.raises(FrameError, match=r"carries 84x84 rgb8 .* got 64x48 rgb8"):
            pub.publish(np.zeros((48, 64, 3), np.uint8), 0)
        with pytest.raises(FrameError, match=r"carries 84x84 rgb8 .* got 84x84 bgr8"):
            pub.publish(np.zeros((84, 84, 3), np.uint8), 0, encoding="bgr8")
        assert sub.latest() is None and sub.received == 0
        pub.publish(np.zeros((84, 84, 3), np.uint8), 5)  # the publisher still works
        latest = sub.latest()
        assert latest is not None and latest.header.stamp_ns == 5


def test_bad_camera_settings_are_named() -> None:
    with pytest.raises(ConfigError, match="rate_hz"):
        SimCameraConfig(rate_hz=0)
    with pytest.raises(ConfigError, match="8192"):
        SimCameraConfig(width=0)
    with pytest.raises(ConfigError, match="encoding"):
        FrameSpec(width=8, height=8, encoding="yuv422")
    with pytest.raises(ConfigError, match="camera name"):
        camera_topic("a/b")


async def test_an_unknown_mjcf_camera_is_named_with_the_ones_the_arm_has() -> None:
    async with open_domain() as domain:
        with pytest.raises(ConfigError, match=r"no camera 'top'.*'scene'.*'wrist'"):
            async with open_sim_cameras("rx200", domain=domain, cameras=[SimCameraConfig(camera="top")]):
                pass


def test_no_egl_names_the_debian_packages(monkeypatch: pytest.MonkeyPatch) -> None:
    # a mock: this machine has EGL, so its absence is simulated at the library lookup
    import ctypes.util

    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None)
    with pytest.raises(RenderError, match="libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1"):
        _try_backend("egl")
    with pytest.raises(RenderError, match="libosmesa6"):
        _try_backend("osmesa")


@pytest.mark.slow
async def test_cameras_rendered_in_a_child_process_and_the_child_ends_with_the_node() -> None:
    from _processes import wait_gone

    cams = [SimCameraConfig(camera="scene", width=64, height=48), SimCameraConfig(camera="wrist", rate_hz=10)]
    async with (
        open_domain() as domain,
        open_servo_sim("rx200", domain=domain),
        open_node("viewer", domain=domain) as viewer,
    ):
        async with open_sim_cameras("rx200", domain=domain, cameras=cams, render="process") as node:
            assert node.render_mode == "process"
            pid = node._process.pid
            assert pid is not None and pid != os.getpid()
            scene = await viewer.create_subscription(Image, node.topic(0))
            wrist = await viewer.create_subscription(Image, node.topic(1))
            async with asyncio.timeout(30):
                a = await scene.receive()
                b = await scene.receive()
                w = await wrist.receive()
            assert a.data.shape == (48, 64, 3) and w.data.shape == (84, 84, 3) and a.data.std() > 10
            assert b.header.seq > a.header.seq and not np.shares_memory(a.data, b.data)  # each frame its own array
            assert node.stats[0].render_ns
        assert wait_gone([pid], 10.0) == []  # no orphan: the render process ended with the node
