"""What the scene is fed from: a live domain (``view_domain``) or a bag (``view_bag``).

A live view subscribes to every topic of a drawn type (JointState, JointCommand, Marker, Image) and looks for new
ones every ``discover_interval_s``; a bag's view logs every drawn message at its log time, and the viewer's time
slider then walks through it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from uniros_async.view import ViewError
from uniros_async.view.scene import SceneLogger

__all__ = ["DRAWN_TYPES", "open_recording", "view_bag", "view_domain"]

logger = logging.getLogger(__name__)

DRAWN_TYPES = ("JointState", "JointCommand", "Marker", "Image")


def open_recording(grpc_url: str, name: str) -> Any:
    """A Rerun recording named ``name`` that sends to the viewer's proxy at ``grpc_url``."""
    import rerun as rr

    rec = rr.RecordingStream("uniros_view", recording_id=name)
    rec.connect_grpc(grpc_url)
    return rec


async def view_domain(
    domain: str | None,
    recording: Any,
    *,
    duration_s: float | None = None,
    arm_wait_s: float = 5.0,
    discover_interval_s: float = 1.0,
    started: Callable[[list[str]], Any] | None = None,
) -> SceneLogger:
    """Draw ``domain``'s arms into ``recording`` until ``duration_s`` (None: until cancelled).

    Args:
        domain: the domain URI (None: ``$UNIROS_DOMAIN``).
        recording: from ``open_recording``.
        duration_s: how long to view.
        arm_wait_s: how long to wait for a first arm (a JointState topic) to appear.
        discover_interval_s: how often to look for new topics.
        started: called with the drawn topics once subscribed.

    Raises:
        ViewError: no arm in the domain within ``arm_wait_s`` (names the domain and its topics).
        DomainError: the domain cannot be reached.
    """
    from uniros_async.bus import latest, open_node, reliable
    from uniros_async.bus.messages import message_type

    scene = SceneLogger(recording)
    name = f"uniros_view_{os.getpid()}_{time.monotonic_ns() % 10**6}"
    async with open_node(name, domain=domain) as node:
        t_wait = time.monotonic() + arm_wait_s
        while True:
            topics = {t["topic"]: t["type"] for t in await node.list_topics()}
            if any(ty == "JointState" for ty in topics.values()):
                break
            if time.monotonic() > t_wait:
                listed = ", ".join(sorted(topics)) or "none"
                raise ViewError(
                    f"no arm in the domain {node.domain_uri}: no JointState topic within {arm_wait_s} s "
                    f"(its topics: {listed})"
                )
            await asyncio.sleep(0.2)
        subs: dict[str, Any] = {}

        async def subscribe(topic: str, type_name: str) -> None:
            def on_msg(msg: Any, topic: str = topic) -> None:
                header = getattr(msg, "header", None)
                stamp = header.stamp_ns if header is not None and header.stamp_ns > 0 else node.now_ns()
                scene.log(topic, msg, stamp)

            # markers come in bursts (a task's goal, end effector, bounds): each one counts; of the rest the newest
            qos = reliable(64) if type_name == "Marker" else latest()
            subs[topic] = await node.create_subscription(message_type(type_name), topic, on_msg, qos=qos)

        async def discover() -> None:
            for t in await node.list_topics():
                if t["type"] in DRAWN_TYPES and t["topic"] not in subs:
                    await subscribe(t["topic"], t["type"])

        await discover()
        if started is not None:
            started(sorted(subs))
        t_end = None if duration_s is None else time.monotonic() + duration_s
        while t_end is None or time.monotonic() < t_end:
            wait = (
                discover_interval_s if t_end is None else max(0.0, min(discover_interval_s, t_end - time.monotonic()))
            )
            await asyncio.sleep(wait)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(5.0):
                    await discover()
    return scene


def view_bag(path: str | os.PathLike[str], recording: Any) -> SceneLogger:
    """Draw every drawn message of the bag at ``path`` into ``recording``, at its log time.

    Raises:
        BagError: not a bag, or a message that does not decode (names the offset); damage past which nothing reads
            is logged as a warning, and what came before it is drawn.
    """
    from uniros_async.bag import BagReader

    reader = BagReader(Path(path))
    info = reader.info()
    topics = [t.topic for t in info.topics.values() if t.type_name in DRAWN_TYPES]
    if not any(t.type_name == "JointState" for t in info.topics.values()):
        raise ViewError(f"no arm in the bag {path}: no JointState topic (its topics: "
                        f"{', '.join(sorted(info.topics)) or 'none'})")  # fmt: skip
    scene = SceneLogger(recording)
    for m in reader.messages(topics, strict=False):
        scene.log(m.topic, m.message, m.log_time_ns)
    if reader.damage is not None:
        logger.warning("%s", reader.damage)
    return scene
