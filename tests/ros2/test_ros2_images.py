"""Camera topics of a ROS 2 driver on the bus: sensor_msgs/msg/Image (padded rows) and CompressedImage (PNG,
decoded by OpenCV off the loop), from a real rclpy publisher, republished as our Image with its pixels exact."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

from uniros_async.adapters.ros_images import open_ros2_camera
from uniros_async.bench.ros2_peers import rclpy_process, wait_for_line
from uniros_async.bus import open_domain, open_node
from uniros_async.bus.messages import Image

CAMERA = Path(__file__).parent / "rclpy_camera.py"
W, H = 64, 48

pytestmark = pytest.mark.slow


def _pattern(k: int) -> np.ndarray:
    y, x = np.mgrid[0:H, 0:W]
    return np.stack([(x * 4 + k) % 256, (y * 5) % 256, (x + y + 3 * k) % 256], axis=-1).astype(np.uint8)


@pytest.mark.parametrize("compressed", [False, True])
async def test_an_rclpy_camera_topic_is_republished_with_its_pixels(compressed: bool, tmp_path: Path) -> None:
    ros_topic = "/camera/color/image_raw" + ("/compressed" if compressed else "")
    with rclpy_process(CAMERA, "/camera/color/image_raw", domain_id=0, tmp_path=tmp_path) as proc:
        wait_for_line(proc, "ready", timeout_s=60.0)
        async with (
            open_domain() as domain,
            open_ros2_camera(ros_topic, domain=domain, domain_id=0) as cam,
            open_node("viewer", domain=domain) as viewer,
        ):
            assert cam.topic == "/camera/color/image_raw"
            async with asyncio.timeout(30):
                await cam.first.wait()
            sub = await viewer.create_subscription(Image, cam.topic)
            async with asyncio.timeout(30):
                frames = [await sub.receive() for _ in range(3)]
            for f in frames:
                k = f.header.stamp_ns - 1_000_000_000  # the driver's stamp: sec 1, nanosec k
                assert 0 < k < 10_000 and f.encoding == "rgb8" and f.data.shape == (H, W, 3)
                assert np.array_equal(f.data, _pattern(k)), "padded rows or decoding lost pixels"
            assert cam.rejected == 0 and cam.published >= 3
