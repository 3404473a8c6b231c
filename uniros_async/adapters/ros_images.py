"""Camera topics of ROS drivers on the bus: ``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage``.

A ROS camera driver (realsense2_camera, usb_cam, v4l2_camera) publishes ``sensor_msgs/Image`` on
``.../image_raw`` and, through image_transport, ``sensor_msgs/CompressedImage`` on ``.../image_raw/compressed``
(JPEG or PNG). ``RosImageTopic`` republishes either as our ``Image`` on a camera topic (camera/topic.py: the ROS
topic's name without ``/compressed``), with ``latest`` QoS:

- a raw frame's rows are read where the ROS message holds them (``step`` may pad them), then copied once into the
  frame's loan (``ImagePublisher.loan``: with one subscriber in another process over shm, its place in the ring);
- a compressed frame is decoded by OpenCV (``cv2.imdecode``) in a worker thread, never on the loop's thread, and
  converted to ``rgb8``. While one decodes, only the newest frame that arrives waits (``dropped`` counts the
  others).

The topic's frame size and encoding are those of its first frame; a frame that differs is refused
(``rejected``, logged with both), as is one in an encoding other than rgb8, bgr8 or mono8, or one that does not
decode. ``open_ros2_camera`` runs one for a ROS 2 topic (``adapters/ros2``); ``open_ros1_camera`` for a ROS 1
topic (``adapters/ros1``). The frame's stamp is the ROS header's (ROS time, nanoseconds); its frame_id is the first
frame's ``header.frame_id``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from typing import Any

import numpy as np

from uniros_async.bus import open_node
from uniros_async.camera.topic import ENCODINGS, FrameSpec, ImagePublisher
from uniros_async.errors import ConfigError, FrameError, TransportClosedError

__all__ = ["RosImageTopic", "decode_compressed", "image_array", "open_ros1_camera", "open_ros2_camera"]

logger = logging.getLogger(__name__)


def image_array(height: int, width: int, encoding: str, step: int, data: Any) -> np.ndarray:
    """The pixels of a ``sensor_msgs/Image`` as an (height, width, channels) uint8 view of ``data``.

    Raises:
        FrameError: an encoding other than ``ENCODINGS``, or ``step`` / ``data`` too short for the size (named).
    """
    if encoding not in ENCODINGS:
        raise FrameError(f"sensor_msgs/Image encoding {encoding!r}: expected one of {sorted(ENCODINGS)}")
    c = ENCODINGS[encoding]
    buf = np.frombuffer(data, np.uint8)
    if height < 1 or width < 1 or step < width * c or buf.size < step * height:
        raise FrameError(
            f"sensor_msgs/Image of {width}x{height} {encoding}: expected step >= {width * c} and "
            f"{step}*{height} bytes of data, got step {step} and {buf.size} bytes"
        )
    return buf[: step * height].reshape(height, step)[:, : width * c].reshape(height, width, c)


def decode_compressed(fmt: str, data: Any) -> np.ndarray:
    """A ``sensor_msgs/CompressedImage``'s picture as rgb8 (OpenCV's ``imdecode``; blocking: run it off the loop).

    Raises:
        FrameError: OpenCV cannot decode it (``fmt`` named), or OpenCV is missing (what to install).
    """
    try:
        import cv2
    except ImportError:
        raise FrameError("decoding CompressedImage needs OpenCV: pip install 'uniros-async[camera]'") from None
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise FrameError(f"sensor_msgs/CompressedImage of format {fmt!r}: OpenCV could not decode its data")
    return np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))


class RosImageTopic:
    """One ROS image topic republished on the bus (``on_ros`` from the ROS side's callback, ``run`` as a task).

    Attributes:
        topic: our camera topic.
        compressed: whether the ROS topic carries ``CompressedImage``.
        publisher: our ImagePublisher, made on the first frame (its size and encoding are the topic's).
        published, dropped, rejected: frames republished; waiting frames replaced by a newer one; frames refused.
    """

    def __init__(self, node: Any, topic: str, *, compressed: bool) -> None:
        self.node = node
        self.topic = topic
        self.compressed = compressed
        self.publisher: ImagePublisher | None = None
        self.published = 0
        self.dropped = 0
        self.rejected = 0
        self.first = asyncio.Event()
        self._pending: tuple[Any, int] | None = None
        self._wake = asyncio.Event()

    def on_ros(self, msg: Any, stamp_ns: int) -> None:
        """Take a ROS message (any client library's: the fields are sensor_msgs'); never waits."""
        if self._pending is not None:
            self.dropped += 1
        self._pending = (msg, stamp_ns)
        self._wake.set()

    async def run(self) -> None:
        """Republish frames until cancelled."""
        while True:
            await self._wake.wait()
            self._wake.clear()
            pending, self._pending = self._pending, None
            if pending is None:
                continue
            msg, stamp_ns = pending
            try:
                if self.compressed:
                    frame = await asyncio.to_thread(decode_compressed, str(msg.format), msg.data)
                    encoding = "rgb8"
                else:
                    encoding = str(msg.encoding)
                    frame = image_array(int(msg.height), int(msg.width), encoding, int(msg.step), msg.data)
                pub = self.publisher
                if pub is None:
                    h, w = frame.shape[:2]
                    spec = FrameSpec(width=w, height=h, encoding=encoding)
                    frame_id = str(msg.header.frame_id) or self.topic.strip("/").split("/")[0]
                    pub = self.publisher = await ImagePublisher.create(self.node, self.topic, spec, frame_id=frame_id)
                pub.check(frame, encoding)
                async with pub.loan(stamp_ns) as out:
                    np.copyto(out, frame)
            except FrameError as exc:
                self.rejected += 1
                if self.rejected < 10 or self.rejected % 1000 == 0:
                    logger.warning("%s: refused frame %d: %s", self.topic, self.rejected, exc)
                continue
            except TransportClosedError:
                return
            self.published += 1
            self.first.set()


def _bus_topic(ros_topic: str, topic: str | None) -> str:
    if topic is not None:
        return topic
    return ros_topic.removesuffix("/compressed")


@contextlib.asynccontextmanager
async def open_ros2_camera(
    ros_topic: str,
    *,
    domain: Any,
    topic: str | None = None,
    compressed: bool | None = None,
    domain_id: int | None = None,
    localhost_only: bool = True,
    node_name: str = "ros2_camera",
) -> AsyncIterator[RosImageTopic]:
    """Republish the ROS 2 image topic ``ros_topic`` on ``domain`` for the duration of the block.

    Args:
        ros_topic: the driver's absolute topic, e.g. ``/camera/camera/color/image_raw`` (``.../compressed``: a
            CompressedImage topic, unless ``compressed`` says otherwise).
        topic: our camera topic; None: ``ros_topic`` without ``/compressed``.
        domain_id, localhost_only: the ROS 2 domain and discovery range (``open_ros2_node``).

    Raises:
        ConfigError: ``ros_topic`` is not absolute, or the ROS 2 side is not installed (what to install).
    """
    from uniros_async.adapters.ros2.node import SENSOR_DATA, open_ros2_node

    if not ros_topic.startswith("/"):
        raise ConfigError(f"ROS 2 camera topic: expected an absolute topic like /camera/image_raw, got {ros_topic!r}")
    is_compressed = ros_topic.endswith("/compressed") if compressed is None else compressed
    ros_type = "sensor_msgs/msg/CompressedImage" if is_compressed else "sensor_msgs/msg/Image"
    async with (
        open_ros2_node(node_name, domain_id=domain_id, localhost_only=localhost_only) as ros,
        open_node(node_name, domain=domain) as node,
        asyncio.TaskGroup() as tg,
    ):
        cam = RosImageTopic(node, _bus_topic(ros_topic, topic), compressed=is_compressed)

        def on_ros(msg: Any) -> None:
            stamp = msg.header.stamp
            cam.on_ros(msg, int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec))

        ros.create_subscription(ros_topic, ros_type, on_ros, qos=SENSOR_DATA)
        task = tg.create_task(cam.run(), name=f"ros2 camera {ros_topic}")
        try:
            yield cam
        finally:
            task.cancel()


@contextlib.asynccontextmanager
async def open_ros1_camera(
    ros_topic: str,
    *,
    domain: Any,
    topic: str | None = None,
    compressed: bool | None = None,
    master_uri: str | None = None,
    node_name: str = "ros1_camera",
) -> AsyncIterator[RosImageTopic]:
    """Republish the ROS 1 image topic ``ros_topic`` on ``domain`` for the duration of the block.

    Args:
        ros_topic: the driver's absolute topic, e.g. ``/usb_cam/image_raw`` (``.../compressed``: a CompressedImage
            topic, unless ``compressed`` says otherwise).
        topic: our camera topic; None: ``ros_topic`` without ``/compressed``.
        master_uri: the rosmaster (``open_ros1_node``); None: ``$ROS_MASTER_URI``, else ``http://127.0.0.1:11311/``.

    Raises:
        ConfigError: ``ros_topic`` is not absolute.
        RobotError: the master cannot be reached (``open_ros1_node`` names it).
    """
    from uniros_async.adapters.ros1.msgs import CompressedImage
    from uniros_async.adapters.ros1.msgs import Image as Ros1Image
    from uniros_async.adapters.ros1.node import open_ros1_node

    if not ros_topic.startswith("/"):
        raise ConfigError(f"ROS 1 camera topic: expected an absolute topic like /usb_cam/image_raw, got {ros_topic!r}")
    is_compressed = ros_topic.endswith("/compressed") if compressed is None else compressed
    msg_type: Any = CompressedImage if is_compressed else Ros1Image
    async with (
        open_ros1_node(f"/uniros_{node_name}", master_uri=master_uri) as ros,
        open_node(node_name, domain=domain) as node,
        asyncio.TaskGroup() as tg,
    ):
        cam = RosImageTopic(node, _bus_topic(ros_topic, topic), compressed=is_compressed)
        await ros.subscribe(ros_topic, msg_type, lambda m: cam.on_ros(m, m.header.stamp_ns))
        task = tg.create_task(cam.run(), name=f"ros1 camera {ros_topic}")
        try:
            yield cam
        finally:
            task.cancel()
