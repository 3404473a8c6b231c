"""Real cameras: a V4L2/UVC device or a video file, captured through OpenCV, as a camera node on the bus.

``uniros camera serve SOURCE`` (or ``open_capture_camera``) opens ``SOURCE`` with OpenCV's ``VideoCapture``
(``/dev/video0``, a device index such as ``0``, or a video file) and publishes its frames as ``Image`` (``rgb8``)
on ``<namespace>/<camera>/color/image_raw`` (camera/topic.py), ``latest`` QoS: over shared memory to the other
processes of the machine, over tcp beyond it.

Capture is blocking I/O, so it runs in a thread of its own: the thread reads a frame (a device paces it; a file is
paced to ``rate_hz``, its own frame rate by default), converts it from OpenCV's BGR to RGB (the one copy, into the
frame published) and hands it to the loop, which publishes it stamped with the instant it was read. At the end of a
file the node stops publishing (``finished`` is set), or starts the file again with ``loop``. A source that cannot
be opened raises ``CameraError`` naming it. Needs the ``camera`` extra (``opencv-python-headless``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from uniros_async.bus import open_node
from uniros_async.bus.tasks import unwrap_task_group
from uniros_async.camera.topic import FrameSpec, ImagePublisher, camera_topic
from uniros_async.errors import CameraError, ConfigError
from uniros_async.transports.base import TransportOptions

__all__ = ["CameraError", "CaptureCameraNode", "CaptureConfig", "open_capture_camera", "serve_camera"]

logger = logging.getLogger(__name__)

DEFAULT_RATE_HZ = 30.0
"""The rate of a source that does not say its own (a device without a frame rate, a file without one)."""
THREAD_JOIN_TIMEOUT_S = 5.0
ADVERTISE_POLL_S = 0.05
"""How often the capture thread, holding its second frame until the topic is advertised, looks whether it should
stop instead."""


@dataclass(frozen=True, kw_only=True)
class CaptureConfig:
    """One captured camera.

    Raises:
        ConfigError: an empty source, a rate outside (0, 240] Hz, or only one of width and height.
    """

    source: str
    """``/dev/videoN``, a device index (``"0"``), or a video file's path."""
    namespace: str = ""
    """The namespace of the camera's topic (e.g. the arm's, ``/rx200``)."""
    camera: str = "camera"
    """The camera's name in its topic: ``<namespace>/<camera>/color/image_raw``."""
    rate_hz: float | None = None
    """Frames per second published; None: the source's own rate (or 30)."""
    width: int | None = None
    """Resize every frame to ``width`` x ``height``; None: the source's size."""
    height: int | None = None
    loop: bool = False
    """Start a video file again at its end, instead of stopping."""

    def __post_init__(self) -> None:
        if not self.source:
            raise ConfigError("camera source: expected /dev/videoN, a device index or a video file, got ''")
        if self.rate_hz is not None and not 0 < self.rate_hz <= 240:
            raise ConfigError(f"camera rate_hz: expected > 0 and <= 240, got {self.rate_hz}")
        if (self.width is None) != (self.height is None):
            raise ConfigError(f"camera size: give both width and height, got {self.width} and {self.height}")
        camera_topic(self.camera, self.namespace)  # ConfigError for a bad camera name


def _cv2() -> Any:
    try:
        import cv2
    except ImportError as exc:
        raise CameraError(
            "capturing a camera needs OpenCV: pip install 'uniros-async[camera]' (opencv-python-headless)"
        ) from exc
    return cv2


def _open_capture(source: str) -> Any:
    """Open ``source`` with OpenCV (blocking: call it off the loop).

    Raises:
        CameraError: it cannot be opened, or gives no frame.
    """
    cv2 = _cv2()
    target: str | int = int(source) if source.isdigit() else source
    cap = cv2.VideoCapture(target)
    if not cap.isOpened():
        cap.release()
        kind = "device" if source.isdigit() or source.startswith("/dev/") else "video file"
        raise CameraError(
            f"cannot open camera source {source!r}: OpenCV's VideoCapture cannot open it as a {kind} (does it "
            "exist, may this user read it, is it a format OpenCV reads?)"
        )
    return cap


class CaptureCameraNode:
    """A captured camera on the bus. Create with ``async with open_capture_camera(config, domain=...)``.

    Attributes:
        config: the camera's settings.
        publisher: its ImagePublisher (``publisher.topic``, ``publisher.spec``).
        frames: frames published.
        finished: set when a video file ended (without ``loop``).
    """

    def __init__(self, node: Any, config: CaptureConfig, cap: Any, rate_hz: float) -> None:
        self.node = node
        self.config = config
        self.rate_hz = rate_hz
        self.frames = 0
        self.finished = asyncio.Event()
        self.publisher: ImagePublisher | None = None
        self._cap = cap
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._failed: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._spec_ready: asyncio.Future[FrameSpec] = asyncio.get_running_loop().create_future()
        self._first: tuple[np.ndarray, int] | None = None
        self._advertised = threading.Event()  # the topic exists: frames after the first can be published
        self._watch: asyncio.Task[None] | None = None

    @property
    def topic(self) -> str:
        """The camera's topic."""
        return camera_topic(self.config.camera, self.config.namespace)

    def _convert(self, cv2: Any, bgr: np.ndarray) -> np.ndarray:
        cfg = self.config
        if cfg.width is not None and cfg.height is not None and bgr.shape[:2] != (cfg.height, cfg.width):
            bgr = cv2.resize(bgr, (cfg.width, cfg.height), interpolation=cv2.INTER_AREA)
        if bgr.ndim == 2:
            return np.asarray(cv2.cvtColor(bgr, cv2.COLOR_GRAY2RGB))
        return np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))

    def _run(self, loop: asyncio.AbstractEventLoop) -> None:
        cv2 = _cv2()
        period_s = 1.0 / self.rate_hz
        next_t = time.monotonic()
        try:
            while not self._stop.is_set():
                ok, bgr = self._cap.read()
                stamp = time.monotonic_ns()
                if not ok:
                    if self.config.loop and self.frames > 0:
                        self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                        continue
                    loop.call_soon_threadsafe(self._end)
                    return
                frame = self._convert(cv2, bgr)
                loop.call_soon_threadsafe(self._publish, frame, stamp)
                if not self._advertised.is_set():
                    # the first frame gives the topic its size; the next waits until the topic exists, so that a
                    # video file loses no frame to the advertising
                    while not self._advertised.wait(ADVERTISE_POLL_S):
                        if self._stop.is_set():
                            return
                    next_t = time.monotonic()
                next_t += period_s
                delay = next_t - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)
                else:
                    next_t = time.monotonic()  # a device slower than the rate: no burst to catch up
        except BaseException as exc:  # noqa: BLE001 - handed to the loop, which raises it in the node's task group
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(_fail, self._failed, exc)
        finally:
            self._cap.release()

    def _publish(self, frame: np.ndarray, stamp_ns: int) -> None:
        if not self._spec_ready.done():
            h, w = frame.shape[:2]
            self._spec_ready.set_result(FrameSpec(width=w, height=h))
            self._first = frame, stamp_ns  # published once the topic is advertised with its size
            return
        if self.publisher is None:
            return
        self.publisher.publish(frame, stamp_ns)
        self.frames += 1

    def _end(self) -> None:
        logger.info("%s: the source %s ended after %d frames", self.topic, self.config.source, self.frames)
        if not self._spec_ready.done():
            self._spec_ready.set_exception(CameraError(f"camera source {self.config.source!r} gave no frame"))
        self.finished.set()

    async def _start(self, tg: asyncio.TaskGroup) -> None:
        loop = asyncio.get_running_loop()
        self._thread = threading.Thread(
            target=self._run, args=(loop,), name=f"capture {self.config.source}", daemon=True
        )
        self._thread.start()
        self._watch = tg.create_task(self._watch_thread(), name="capture thread watch")
        async with asyncio.timeout(10.0):  # the first frame gives the topic's size
            waits: list[asyncio.Future[Any]] = [self._spec_ready, self._failed]
            await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
        if self._failed.done():
            self._failed.result()
        spec = self._spec_ready.result()
        self.publisher = await ImagePublisher.create(self.node, self.topic, spec, frame_id=self.config.camera)
        assert self._first is not None
        frame, stamp = self._first
        self.publisher.publish(frame, stamp)
        self.frames += 1
        self._advertised.set()

    async def _watch_thread(self) -> None:
        await self._failed

    async def _shutdown(self) -> None:
        if self._watch is not None:
            self._watch.cancel()
        self._stop.set()
        if self._thread is not None:
            await asyncio.to_thread(self._thread.join, THREAD_JOIN_TIMEOUT_S)


def _fail(future: asyncio.Future[None], exc: BaseException) -> None:
    if not future.done():
        future.set_exception(exc)


@contextlib.asynccontextmanager
async def open_capture_camera(
    config: CaptureConfig,
    *,
    domain: Any = None,
    node_name: str = "",
    transport: str = "auto",
    options: TransportOptions | None = None,
) -> AsyncIterator[CaptureCameraNode]:
    """Capture ``config.source`` and publish its frames for the duration of the block.

    Args:
        config: the source and the topic.
        domain: the Domain (or its URI) to join; None: ``$UNIROS_DOMAIN``.
        node_name: the node's name; default ``<camera>_capture``.
        transport: the node's transport choice.
        options: transport options.

    Yields:
        The running CaptureCameraNode, its first frame published.

    Raises:
        CameraError: the source cannot be opened or gives no frame within 10 s (named), or OpenCV is missing.
    """
    cap = await asyncio.to_thread(_open_capture, config.source)
    rate = config.rate_hz
    if rate is None:
        fps = float(cap.get(_cv2().CAP_PROP_FPS) or 0.0)
        rate = fps if 0 < fps <= 240 else DEFAULT_RATE_HZ
    ns = config.namespace or "/"
    name = node_name or f"{config.camera}_capture"
    cam: CaptureCameraNode | None = None
    try:
        async with open_node(name, domain=domain, namespace=ns, transport=transport, options=options) as node:
            cam = CaptureCameraNode(node, config, cap, rate)
            async with unwrap_task_group() as tg:
                try:
                    await cam._start(tg)
                    yield cam
                finally:
                    await cam._shutdown()
    finally:
        if cam is None or cam._thread is None:  # the capture thread, once started, releases it
            cap.release()


async def serve_camera(
    config: CaptureConfig, *, domain: str | None = None, on_ready: Callable[[str, str], Any] | None = None
) -> None:
    """Serve a captured camera until cancelled (or a video file ends, without ``loop``).

    With ``domain`` None and no ``$UNIROS_DOMAIN`` a domain of its own is opened on 127.0.0.1. ``on_ready`` gets
    the domain's URI and the camera's topic once the first frame is out.
    """
    import os

    from uniros_async.bus import open_domain

    async with contextlib.AsyncExitStack() as stack:
        uri = domain or os.environ.get("UNIROS_DOMAIN")
        if not uri:
            uri = (await stack.enter_async_context(open_domain())).uri
        cam = await stack.enter_async_context(open_capture_camera(config, domain=uri))
        if on_ready is not None:
            on_ready(uri, cam.topic)
        await cam.finished.wait()
