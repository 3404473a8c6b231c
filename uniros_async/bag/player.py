"""Play a bag into a domain (``uniros bag play``): each message published on its topic, at its log time.

A thread reads and decodes the bag ahead into a bounded queue, so the loop that publishes never waits on the disk.
Messages keep their content (stamps included) and go out in the bag's order, each when its log time has come:

- on the wall clock, ``(log_time - first log_time) / rate`` after play began;
- on the sim clock, the player is the domain's time source: before each message it publishes the message's log
  time as a ``ClockTick`` on ``/clock`` (the bag's own ``/clock`` is not replayed), paced on the wall clock by
  ``rate`` sim seconds per wall second, or as fast as it can with ``rate=0``.

``loop`` plays the bag again at its end; on the sim clock each round's times follow the last one's, so the clock
never goes back.
"""

from __future__ import annotations

import asyncio
import dataclasses
import os
import queue
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from uniros_async.bag.reader import BagMessage, BagReader
from uniros_async.errors import ConfigError

__all__ = ["PlayConfig", "play"]

_END = object()


@dataclasses.dataclass(frozen=True, slots=True)
class PlayConfig:
    """What ``play`` plays and how.

    Args:
        path: the bag.
        domain: the domain's URI (None: ``$UNIROS_DOMAIN``).
        topics: only these (one may be given as a string; empty: all).
        rate: playback speed (2.0: twice as fast); 0 on the sim clock: as fast as possible.
        loop: start again at the end, until cancelled.
        clock: "wall", or "sim" to publish the bag's time on ``/clock``.
        wait_subscribers: first wait until every topic has this many subscribers (at most ``wait_timeout_s``).
        wait_timeout_s: how long to wait for them.
    """

    path: str | os.PathLike[str]
    domain: str | None = None
    topics: Sequence[str] = ()
    rate: float = 1.0
    loop: bool = False
    clock: str = "wall"
    wait_subscribers: int = 0
    wait_timeout_s: float = 10.0

    def __post_init__(self) -> None:
        if isinstance(self.topics, str):  # one topic given as a string: that topic, not its letters
            object.__setattr__(self, "topics", (self.topics,))
        if self.clock not in ("wall", "sim"):
            raise ConfigError(f"play clock: expected 'wall' or 'sim', got {self.clock!r}")
        if not (self.rate > 0 or (self.rate == 0 and self.clock == "sim")):
            raise ConfigError(f"play rate: expected > 0 (or 0 on the sim clock: as fast as possible), got {self.rate}")
        if self.wait_subscribers < 0:
            raise ConfigError(f"play wait_subscribers: expected >= 0, got {self.wait_subscribers}")


def _read_ahead(reader: BagReader, topics: set[str] | None, out: queue.Queue[Any], stop: threading.Event) -> None:
    try:
        for m in reader.messages(topics):
            while not stop.is_set():
                try:
                    out.put(m, timeout=0.1)
                    break
                except queue.Full:
                    continue
            if stop.is_set():
                return
        out.put(_END)
    except BaseException as exc:  # handed to the loop, raised there
        out.put(exc)


async def play(config: PlayConfig) -> int:
    """Publish the bag's messages into the domain (see the module docstring); returns how many were published.

    Raises:
        BagError: the bag cannot be read (a damaged bag plays up to the damage, then raises naming the offset).
        DomainError: the domain cannot be reached. TimeoutError: too few subscribers after ``wait_timeout_s``.
    """
    from uniros_async.bus import open_node, reliable
    from uniros_async.bus.messages import ClockTick, message_type

    reader = BagReader(Path(config.path))
    info = reader.info()
    if info.damage and not info.topics:
        raise reader.damage or ConfigError(info.damage)
    topics = set(config.topics) or None
    sim = config.clock == "sim"
    played = 0
    async with open_node(f"uniros_bag_play_{os.getpid()}_{time.monotonic_ns() % 10**6}", domain=config.domain) as node:
        pubs: dict[str, Any] = {}
        for t in info.topics.values():
            if (topics is None or t.topic in topics) and not (sim and t.topic == "/clock"):
                pubs[t.topic] = await node.create_publisher(message_type(t.type_name), t.topic, qos=reliable(1000))
        # every tick reaches a follower, as the bag's messages do: a recorder on the sim clock stamps each message with
        # the tick published just before it, and a tick kept only as the latest could be replaced before it was sent
        clock_pub = await node.create_publisher(ClockTick, "/clock", qos=reliable(1000)) if sim else None
        for p in [*pubs.values(), *([clock_pub] if clock_pub is not None else [])]:
            await p.wait_for_subscribers(config.wait_subscribers, timeout_s=config.wait_timeout_s)
        offset_ns = 0
        while True:
            q: queue.Queue[Any] = queue.Queue(maxsize=256)
            stop = threading.Event()
            thread = threading.Thread(target=_read_ahead, args=(reader, topics, q, stop), daemon=True)
            thread.start()
            t0_wall = time.monotonic()
            first_ns: int | None = None
            last_ns = 0
            try:
                while True:
                    try:
                        item = q.get_nowait()
                    except queue.Empty:
                        try:  # bounded, so that a cancelled play leaves no thread waiting on an empty queue
                            item = await asyncio.to_thread(q.get, True, 0.2)
                        except queue.Empty:
                            continue
                    if item is _END:
                        break
                    if isinstance(item, BaseException):
                        raise item
                    m: BagMessage = item
                    if first_ns is None:
                        first_ns = m.log_time_ns
                    last_ns = m.log_time_ns
                    pub = pubs.get(m.topic)
                    if pub is None:
                        continue
                    if config.rate > 0:
                        due = t0_wall + (m.log_time_ns - first_ns) / 1e9 / config.rate
                        wait_s = due - time.monotonic()
                        if wait_s > 0:
                            await asyncio.sleep(wait_s)
                    if clock_pub is not None:
                        clock_pub.publish(ClockTick(sim_time_ns=m.log_time_ns + offset_ns))
                    pub.publish(m.message)
                    played += 1
                    if config.rate == 0 and played % 64 == 0:
                        await asyncio.sleep(0)  # let the node's senders run
            finally:
                stop.set()
                await asyncio.to_thread(thread.join)
            if not config.loop or first_ns is None:
                break
            offset_ns += last_ns - first_ns + 1
        # the node's senders drain their queues (bounded: a subscriber that stopped reading is left) before it closes
        for p in pubs.values():
            for _ in range(int(config.wait_timeout_s / 0.01)):
                if not any(s.queue for s in p._sinks):
                    break
                await asyncio.sleep(0.01)
    return played
