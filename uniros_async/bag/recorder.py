"""Record topics of a domain into a bag (``uniros bag record``).

A recorder is a node of the domain. It subscribes to each topic with ``reliable(depth)``: a publisher's outgoing
queue to it is bounded, so a recorder that falls behind makes that queue drop its oldest frames (counted by the
publisher), never makes a publisher wait. Each message's callback only hands it to the BagWriter, whose thread
encodes, compresses and writes; the writer's own queue is bounded in messages and bytes, and what it drops is
counted per topic. Log times are the recorder's clock: the wall clock, or with ``clock="sim"`` the time of the
domain's ``/clock`` (a follower SimClock).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import difflib
import logging
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from uniros_async.bag.errors import BagError
from uniros_async.bag.writer import BagWriter, WriterStats
from uniros_async.errors import CodecError, ConfigError

__all__ = ["RecordConfig", "closest_topics", "record"]

logger = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True, slots=True)
class RecordConfig:
    """What ``record`` records and how.

    Args:
        path: the MCAP file to write.
        topics: the topics (one may be given as a string); empty: every topic of the domain, including those that
            appear while recording.
        domain: the domain's URI (None: ``$UNIROS_DOMAIN``).
        duration_s: stop after this many seconds of the recorder's clock (None: until cancelled).
        clock: "wall", or "sim" to stamp log times with the domain's ``/clock``.
        depth: each subscription's reliable queue depth (at the publisher and here).
        compression: "zstd" or "lz4" chunks (or "none").
        discover_interval_s: how often to look for new topics when recording all.
    """

    path: str | os.PathLike[str]
    topics: Sequence[str] = ()
    domain: str | None = None
    duration_s: float | None = None
    clock: str = "wall"
    depth: int = 100
    compression: str = "zstd"
    discover_interval_s: float = 1.0

    def __post_init__(self) -> None:
        if isinstance(self.topics, str):  # one topic given as a string: that topic, not its letters
            object.__setattr__(self, "topics", (self.topics,))
        if self.clock not in ("wall", "sim"):
            raise ConfigError(f"record clock: expected 'wall' or 'sim', got {self.clock!r}")
        if self.duration_s is not None and self.duration_s <= 0:
            raise ConfigError(f"record duration_s: expected > 0 or None, got {self.duration_s}")
        if self.depth < 1:
            raise ConfigError(f"record depth: expected >= 1, got {self.depth}")


def closest_topics(name: str, topics: Sequence[str], n: int = 3) -> list[str]:
    """The ``n`` topics of ``topics`` whose names are closest to ``name`` (by difflib's ratio, then by the last
    name segment), for an error message."""
    close = difflib.get_close_matches(name, topics, n=n, cutoff=0.4)
    if not close:
        tail = name.rstrip("/").rsplit("/", 1)[-1]
        close = [t for t in topics if tail and tail in t][:n]
    return close


async def record(
    config: RecordConfig,
    *,
    started: Callable[[list[str]], Any] | None = None,
    stop: asyncio.Event | None = None,
) -> WriterStats:
    """Record ``config.topics`` of the domain into ``config.path`` until ``config.duration_s``, ``stop`` is set or
    the task is cancelled; then close the bag and return what was written and dropped.

    Args:
        config: what to record.
        started: called with the topics once subscribed (``uniros bag record`` prints them).
        stop: set it to stop recording.

    Raises:
        BagError: a topic not in the domain (names the domain's closest topics); the bag cannot be written (a full
            disk: the file reads up to its last complete chunk).
        DomainError: the domain cannot be reached.
    """
    from uniros_async.bus import open_node, reliable
    from uniros_async.bus.messages import message_type

    clock: Any = None
    if config.clock == "sim":
        from uniros_async.sim_clock import SimClock

        clock = SimClock(follower=True)
    name = f"uniros_bag_record_{os.getpid()}_{time.monotonic_ns() % 10**6}"
    async with open_node(name, domain=config.domain, clock=clock) as node:
        if clock is not None:
            from uniros_async.sim_clock import follow_clock

            await follow_clock(node, clock)
        known = {t["topic"]: t["type"] for t in await node.list_topics()}
        wanted = list(dict.fromkeys(node.resolve(t) for t in config.topics))
        for topic in wanted:
            if topic not in known:
                close = closest_topics(topic, sorted(known))
                hint = f"closest: {', '.join(close)}" if close else f"its topics: {', '.join(sorted(known)) or 'none'}"
                raise BagError(f"no topic {topic!r} in the domain {node.domain_uri}; {hint}")
        writer = BagWriter(
            Path(config.path),
            compression=config.compression,
            metadata={"uniros": {"domain": str(node.domain_uri), "clock": config.clock, "recorder": name}},
        )
        subs: dict[str, Any] = {}

        async def subscribe(topic: str, type_name: str) -> None:
            try:
                cls = message_type(type_name)
            except CodecError:
                logger.warning("%s: type %s is not registered in this process; not recorded", topic, type_name)
                subs[topic] = None
                return

            def on_msg(msg: Any, topic: str = topic) -> None:
                header = getattr(msg, "header", None)
                now = node.now_ns()
                writer.put(topic, msg, now, header.stamp_ns if header is not None and header.stamp_ns >= 0 else now)

            subs[topic] = await node.create_subscription(cls, topic, on_msg, qos=reliable(config.depth))

        try:
            for topic in wanted or sorted(known):
                await subscribe(topic, known[topic])
            if started is not None:
                started(sorted(t for t, s in subs.items() if s is not None))
            t_end = None if config.duration_s is None else node.now_ns() + int(config.duration_s * 1e9)
            stop = stop or asyncio.Event()
            while not stop.is_set():
                if writer.error is not None:
                    break
                wait_s = config.discover_interval_s
                if t_end is not None:
                    left_s = (t_end - node.now_ns()) / 1e9
                    if left_s <= 0:
                        break
                    wait_s = min(wait_s, left_s) if clock is None else min(wait_s, 0.05)
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(wait_s):
                        await stop.wait()
                if not wanted:
                    for t in await node.list_topics():
                        if t["topic"] not in subs:
                            await subscribe(t["topic"], t["type"])
        finally:
            for sub in subs.values():
                if sub is not None:
                    await sub.aclose()
            stats = await asyncio.to_thread(writer.close)
    return stats
