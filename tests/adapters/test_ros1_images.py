"""Camera topics of a ROS 1 driver on the bus: sensor_msgs/Image (padded rows) and CompressedImage (PNG, decoded
by OpenCV off the loop), from a real rospy publisher against a real rosmaster, republished with exact pixels."""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path

import numpy as np
import pytest

from uniros_async.adapters.ros1.msgs import CompressedImage, Image, RosHeader
from uniros_async.adapters.ros_images import open_ros1_camera
from uniros_async.bench.ros1_peers import rospy_process, wait_for_line
from uniros_async.bus import messages, open_domain, open_node

CAMERA = Path(__file__).with_name("rospy_camera.py")
W, H = 64, 48


def _pattern(k: int) -> np.ndarray:
    y, x = np.mgrid[0:H, 0:W]
    return np.stack([(x * 4 + k) % 256, (y * 5) % 256, (x + y + 3 * k) % 256], axis=-1).astype(np.uint8)


@pytest.mark.slow
@pytest.mark.parametrize("compressed", [False, True])
async def test_a_rospy_camera_topic_is_republished_with_its_pixels(
    compressed: bool, ros_master: str, tmp_path: Path
) -> None:
    ros_topic = "/usb_cam/image_raw" + ("/compressed" if compressed else "")
    with rospy_process(CAMERA, "/usb_cam/image_raw", master_uri=ros_master, tmp_path=tmp_path) as proc:
        wait_for_line(proc, "ready", timeout_s=60.0)
        async with (
            open_domain() as domain,
            open_ros1_camera(ros_topic, domain=domain, master_uri=ros_master) as cam,
            open_node("viewer", domain=domain) as viewer,
        ):
            assert cam.topic == "/usb_cam/image_raw"
            async with asyncio.timeout(30):
                await cam.first.wait()
            sub = await viewer.create_subscription(messages.Image, cam.topic)
            async with asyncio.timeout(30):
                frames = [await sub.receive() for _ in range(3)]
            for f in frames:
                k = f.header.stamp_ns - 1_000_000_000  # the driver's stamp: secs 1, nsecs k
                assert 0 < k < 10_000 and f.encoding == "rgb8" and f.data.shape == (H, W, 3)
                assert np.array_equal(f.data, _pattern(k)), "padded rows or decoding lost pixels"
            assert cam.rejected == 0 and cam.published >= 3


def test_image_messages_round_trip_through_the_ros1_wire_format() -> None:
    data = np.arange(2 * 8, dtype=np.uint8)
    img = Image(RosHeader(seq=3, stamp_ns=5, frame_id="cam"), 2, 2, "rgb8", 0, 8, data)
    back = Image.deserialize(img.serialize())
    assert (back.height, back.width, back.encoding, back.step, back.header) == (2, 2, "rgb8", 8, img.header)
    assert np.array_equal(back.data, data)
    comp = CompressedImage(RosHeader(frame_id="cam"), "jpeg", np.frombuffer(b"\xff\xd8\xff", np.uint8))
    assert CompressedImage.deserialize(comp.serialize()).data.tobytes() == b"\xff\xd8\xff"


async def test_a_frame_of_another_size_is_refused_and_the_topic_keeps_working() -> None:
    from uniros_async.adapters.ros_images import RosImageTopic

    class Msg:  # the fields of a sensor_msgs/Image, as any client library's message has them
        def __init__(self, h: int, w: int, encoding: str = "rgb8") -> None:
            self.header = RosHeader(frame_id="cam")
            self.height, self.width, self.encoding, self.step = h, w, encoding, w * 3
            self.data = np.zeros(h * w * 3, np.uint8)

    async with open_domain() as domain, open_node("cam", domain=domain) as node, asyncio.TaskGroup() as tg:
        cam = RosImageTopic(node, "/cam/color/image_raw", compressed=False)
        task = tg.create_task(cam.run())
        for msg in (Msg(4, 6), Msg(5, 6), Msg(4, 6, "yuv422"), Msg(4, 6)):
            cam.on_ros(msg, 1)
            for _ in range(20):
                await asyncio.sleep(0)
        assert (cam.published, cam.rejected) == (2, 2)
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
