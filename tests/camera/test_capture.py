"""``uniros camera serve``: a real video file, written by OpenCV here, published by a real process over shm."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2  # the camera extra, part of the test extra
import numpy as np
import pytest

from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import Image
from uniros_async.camera.capture import CameraError, CaptureConfig, open_capture_camera
from uniros_async.errors import ConfigError

N_FRAMES = 12


def _write_video(path: Path, n: int = N_FRAMES) -> Path:
    """A 64x48 MJPG video at 30 fps: pure red (BGR 0,0,255) with a grey square whose level counts the frames."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (64, 48))
    assert writer.isOpened()
    for i in range(n):
        frame = np.zeros((48, 64, 3), np.uint8)
        frame[:, :, 2] = 255
        frame[:16, :16] = 20 * i
        writer.write(frame)
    writer.release()
    return path


def _serve(*args: str, env: dict[str, str]) -> subprocess.Popen[str]:
    cmd = [sys.executable, "-m", "uniros_async.cli", "camera", "serve", *args]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
async def test_camera_serve_publishes_a_video_file_to_another_process(tmp_path: Path) -> None:
    video = _write_video(tmp_path / "clip.avi")
    async with open_domain() as domain, open_node("viewer", domain=domain, namespace="/rx200") as viewer:
        sub = await viewer.create_subscription(Image, "camera/color/image_raw")
        env = {**os.environ, "UNIROS_DOMAIN": domain.uri}
        proc = _serve(str(video), "--namespace", "/rx200", "--loop", "--rate", "30", env=env)
        try:
            frames = []
            async with asyncio.timeout(20):
                while len(frames) < N_FRAMES + 3:  # past the end: the file starts again
                    img = await sub.receive()
                    frames.append((img, time.monotonic_ns()))
            img = frames[-1][0]
            assert img.data.shape == (48, 64, 3) and img.encoding == "rgb8" and img.header.frame_id == "camera"
            r, g, b = img.data[30, 40].astype(int)
            assert r > 230 and g < 30 and b < 30  # OpenCV's BGR came out as RGB
            levels = [int(f.data[4, 4, 0]) for f, _ in frames]
            assert max(levels) > 150 and min(levels) < 30  # the grey square counts up, then the file starts again
            # the frame's age where it is used: stamped at capture on CLOCK_MONOTONIC, one clock on this machine
            ages_ms = [(t - f.header.stamp_ns) / 1e6 for f, t in frames[1:]]
            assert 0 <= np.median(ages_ms) < 200  # a frame, not a backlog: latest QoS
            stamps = np.diff([f.header.stamp_ns for f, _ in frames]) / 1e9
            assert 0.02 < np.median(stamps) < 0.05  # paced at 30 Hz
        finally:
            proc.terminate()
            out, err = proc.communicate(timeout=10)
        assert proc.returncode == 0, err
        assert out.startswith(f"export UNIROS_DOMAIN={domain.uri}")


@pytest.mark.slow
def test_camera_serve_names_a_device_it_cannot_open() -> None:
    proc = _serve("/dev/video97", env={**os.environ, "UNIROS_DOMAIN": "tcp://127.0.0.1:9"})
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert "cannot open camera source '/dev/video97'" in err and "device" in err


async def test_a_video_file_ends_and_the_node_says_so(tmp_path: Path) -> None:
    video = _write_video(tmp_path / "short.avi", n=3)
    async with open_domain() as domain:
        cfg = CaptureConfig(source=str(video), camera="cam", rate_hz=200, width=32, height=24)
        async with open_capture_camera(cfg, domain=domain) as cam:
            assert cam.topic == "/cam/color/image_raw" and cam.publisher is not None
            assert cam.publisher.spec.shape == (24, 32, 3)  # resized
            async with asyncio.timeout(5):
                await cam.finished.wait()
            assert cam.frames == 3


async def test_a_missing_file_is_named(tmp_path: Path) -> None:
    missing = tmp_path / "nope.avi"
    async with open_domain() as domain:
        with pytest.raises(CameraError, match=f"cannot open camera source '{missing}'.*video file"):
            async with open_capture_camera(CaptureConfig(source=str(missing)), domain=domain):
                pass


def test_bad_capture_settings_are_named() -> None:
    with pytest.raises(ConfigError, match="both width and height"):
        CaptureConfig(source="0", width=10)
    with pytest.raises(ConfigError, match="rate_hz"):
        CaptureConfig(source="0", rate_hz=-1)
