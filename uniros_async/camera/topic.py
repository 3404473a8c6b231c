"""Camera topics: their names, the frame each one carries, and a publisher that refuses any other frame.

A camera publishes ``Image`` (bus/messages.py) on the name a RealSense or UVC driver uses under the arm's
namespace: ``/<namespace>/<camera>/color/image_raw`` (``camera_topic``), with ``latest`` QoS (a subscriber gets
the newest frame, never a backlog). Every frame of one topic has one size and encoding (``FrameSpec``);
``ImagePublisher.publish`` checks each frame against it and raises ``FrameError`` naming both, publishing nothing.
The frame's stamp is the instant it shows (the render's joint state, the capture), on the publishing node's clock;
its age is measured where it is used (``frame_age_ns``). ``ImagePublisher.loan`` lends the frame's place in the
subscriber's shared-memory ring, so a renderer's or capture's write into it is the frame's only copy.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from uniros_async.bus.messages import Header, Image
from uniros_async.bus.qos import latest
from uniros_async.errors import ConfigError, FrameError

__all__ = ["ENCODINGS", "FrameError", "FrameSpec", "ImagePublisher", "camera_topic", "frame_age_ns"]

ENCODINGS = {"rgb8": 3, "bgr8": 3, "mono8": 1}
"""The encodings a camera topic may carry (sensor_msgs/image_encodings names) and their channels."""


@dataclass(frozen=True, kw_only=True)
class FrameSpec:
    """The frames of one camera topic: ``height`` x ``width`` pixels in ``encoding``.

    Raises:
        ConfigError: a size outside 1..8192 pixels, or an encoding not in ``ENCODINGS``.
    """

    width: int
    height: int
    encoding: str = "rgb8"

    def __post_init__(self) -> None:
        if not (1 <= self.width <= 8192 and 1 <= self.height <= 8192):
            raise ConfigError(f"camera frame size: expected 1..8192 pixels each way, got {self.width}x{self.height}")
        if self.encoding not in ENCODINGS:
            raise ConfigError(f"camera encoding: expected one of {sorted(ENCODINGS)}, got {self.encoding!r}")

    @property
    def shape(self) -> tuple[int, int, int]:
        """The shape of a frame's ``data``: (height, width, channels)."""
        return (self.height, self.width, ENCODINGS[self.encoding])

    def describe(self) -> str:
        """``"84x84 rgb8"``: width x height and encoding."""
        return f"{self.width}x{self.height} {self.encoding}"


def camera_topic(camera: str, namespace: str = "") -> str:
    """The topic of ``camera``'s colour frames, as a RealSense/UVC driver names it: ``<ns>/<camera>/color/image_raw``.

    Raises:
        ConfigError: ``camera`` is empty or holds a ``/``.
    """
    if not camera or "/" in camera:
        raise ConfigError(f"camera name: expected one name without '/', got {camera!r}")
    ns = namespace.rstrip("/")
    return f"{ns}/{camera}/color/image_raw"


def frame_age_ns(image: Image, received_ns: int, now_ns: int, *, same_clock: bool) -> int:
    """How old ``image`` is at ``now_ns``: since its stamp when its publisher stamps on the reader's clock
    (``same_clock``), else since it arrived (``received_ns``, ``time.monotonic_ns()`` at the subscription)."""
    if same_clock:
        return now_ns - image.header.stamp_ns
    return time.monotonic_ns() - received_ns


class ImagePublisher:
    """A publisher of one camera topic that checks every frame against the topic's ``FrameSpec``.

    Create with ``await ImagePublisher.create(node, topic, spec)``.
    """

    def __init__(self, pub: Any, spec: FrameSpec, frame_id: str) -> None:
        self._pub = pub
        self.spec = spec
        self.frame_id = frame_id
        self.topic: str = pub.topic
        self.seq = 0

    @classmethod
    async def create(cls, node: Any, topic: str, spec: FrameSpec, *, frame_id: str = "") -> ImagePublisher:
        """Advertise ``topic`` (Image, ``latest`` QoS) on ``node``; ``frame_id``: the camera's frame (its name)."""
        pub = await node.create_publisher(Image, topic, qos=latest())
        return cls(pub, spec, frame_id or topic.strip("/").split("/")[-3])

    def check(self, data: np.ndarray, encoding: str) -> None:
        """Raise FrameError unless ``data`` (uint8) and ``encoding`` are this topic's frame."""
        spec = self.spec
        if encoding != spec.encoding or data.dtype != np.uint8 or data.shape != spec.shape:
            h, w = (data.shape + (0, 0))[:2]
            raise FrameError(
                f"{self.topic}: the topic carries {spec.describe()} frames of shape {spec.shape} uint8, got "
                f"{w}x{h} {encoding} of shape {data.shape} {data.dtype}; nothing was published"
            )

    def publish(self, data: np.ndarray, stamp_ns: int, *, encoding: str | None = None) -> Image:
        """Publish ``data`` (not to be changed afterwards: in-process subscribers get it as it is) stamped
        ``stamp_ns``.

        Returns:
            The Image published.

        Raises:
            FrameError: ``data``'s shape, dtype or ``encoding`` is not the topic's (nothing is published).
        """
        enc = self.spec.encoding if encoding is None else encoding
        self.check(data, enc)
        self.seq += 1
        msg = Image(header=Header(stamp_ns=stamp_ns, seq=self.seq, frame_id=self.frame_id), encoding=enc, data=data)
        self._pub.publish(msg)
        return msg

    @contextlib.asynccontextmanager
    async def loan(self, stamp_ns: int) -> AsyncIterator[np.ndarray]:
        """A frame to write in place (``Publisher.loan``): the block writes the whole array (this topic's shape,
        uint8), and the frame is published stamped ``stamp_ns`` when it ends (not if it raises). With one remote
        subscriber over shm the array is the frame's place in its ring, so the write is the frame's only copy.
        Don't use the array after the block."""
        async with self._pub.loan(self.spec.shape, np.uint8) as loan:
            yield loan.array
            self.seq += 1
            header = Header(stamp_ns=stamp_ns, seq=self.seq, frame_id=self.frame_id)
            loan.message = Image(header=header, encoding=self.spec.encoding, data=loan.array)

    @property
    def loaned_in_place(self) -> int:
        """Frames published in place in a subscriber's ring (``loan``)."""
        return int(self._pub.loaned_in_place)

    @property
    def subscription_count(self) -> int:
        """Subscribers connected now."""
        return int(self._pub.subscription_count)

    async def aclose(self) -> None:
        """Stop publishing (idempotent)."""
        await self._pub.aclose()
