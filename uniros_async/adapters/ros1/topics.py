"""ROS 1 topics over TCPROS: what a Ros1Node publishes and subscribes to.

A ``_Subscription`` holds one TCPROS connection per publisher the master names for its topic; a ``_Publication``
holds one link per subscriber that connected to our TCPROS server. Users get handles: ``Ros1Subscriber`` (latest
message, ``receive``, a callback) and ``Ros1Publisher`` (``publish``); several handles of one topic in one node
share its connections. Every task here is started with the node's ``spawn`` (its TaskGroup).
"""

from __future__ import annotations

import asyncio
import collections
import itertools
import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Generic, TypeVar

from uniros_async.adapters.ros1 import _tcpros
from uniros_async.adapters.ros1._xmlrpc import call_ros
from uniros_async.adapters.ros1.msgs import Ros1Message
from uniros_async.backoff import Backoff
from uniros_async.errors import CodecError, TransportClosedError

if TYPE_CHECKING:
    from uniros_async.adapters.ros1.node import Ros1Node

__all__ = ["Ros1Publisher", "Ros1Subscriber"]

logger = logging.getLogger(__name__)

M = TypeVar("M", bound=Ros1Message)

_conn_ids = itertools.count(1)
RETRY_MAX_S = 0.5
"""Longest wait between a subscriber's attempts to reconnect to a publisher the master still lists."""
RETRY_ATTEMPT_S = 1.0
"""Bound on each retry's connection (``requestTopic``, the TCP connect): the first attempt takes the node's
``timeout_s``."""
_MAX_UNACKED_FRAMES = 4096
"""Publication times a subscriber link remembers for frames its peer has not acknowledged; beyond it, neighbouring
frames share an entry (the older time), which can only make a frame look older than it is."""


class _RateLimit:
    """At most one log line per ``period_s`` per key; counts what it suppressed."""

    def __init__(self, period_s: float = 5.0) -> None:
        self._period_s = period_s
        self._last: dict[str, float] = {}
        self.suppressed: dict[str, int] = collections.defaultdict(int)

    def __call__(self, key: str) -> bool:
        now = time.monotonic()
        if now - self._last.get(key, -1e9) >= self._period_s:
            self._last[key] = now
            return True
        self.suppressed[key] += 1
        return False


_log_limit = _RateLimit()


class _Changed:
    """Wakes everyone waiting for a count to change (publishers or subscribers connecting)."""

    def __init__(self) -> None:
        self._event = asyncio.Event()

    def notify(self) -> None:
        event, self._event = self._event, asyncio.Event()
        event.set()

    async def wait_until(self, ready: Callable[[], bool], timeout_s: float | None, what: Callable[[], str]) -> None:
        try:
            async with asyncio.timeout(timeout_s):
                while not ready():
                    await self._event.wait()
        except TimeoutError:
            raise TimeoutError(f"{what()} after {timeout_s} s") from None


def _type_mismatch(topic: str, peer: str, their_type: str, their_md5: str, ours: type[Ros1Message]) -> str:
    return (
        f"{topic}: type mismatch with {peer}: it has {their_type or '?'} (md5 {their_md5 or '?'}), we have "
        f"{ours._type} (md5 {ours._md5sum}); dropping that connection"
    )


# ---------------------------------------------------------------------------------------------- subscribing


class _PublisherConn:
    """Statistics of one connected publisher (for getBusInfo/getBusStats)."""

    def __init__(self, uri: str, callerid: str) -> None:
        self.id = next(_conn_ids)
        self.uri = uri
        self.callerid = callerid
        self.bytes = 0
        self.count = 0


class _Subscription:
    """Our subscription to one topic: a connection task per publisher, fanned out to the handles."""

    def __init__(self, node: Ros1Node, topic: str, msg_type: type[Ros1Message]) -> None:
        self.node = node
        self.topic = topic
        self.msg_type = msg_type
        self.handles: list[Ros1Subscriber[Any]] = []
        self.links: dict[str, asyncio.Task[None]] = {}  # publisher API URI -> its connection task
        self.connected: dict[str, _PublisherConn] = {}
        self.changed = _Changed()
        self.closed = False

    def update_publishers(self, uris: list[str]) -> None:
        """The master's current publisher list: connect to new ones, drop ones no longer listed."""
        if self.closed:
            return
        wanted = {u for u in uris if isinstance(u, str)}
        for uri in list(self.links):
            if uri not in wanted:
                self.links.pop(uri).cancel()
        for uri in wanted - self.links.keys():
            self.links[uri] = self.node._spawn(self._link(uri), name=f"ros1 sub {self.topic} <- {uri}")

    async def _link(self, uri: str) -> None:
        # Like rospy: while the master lists the publisher, reconnect after failures with a growing delay (capped,
        # and each retry's connection bounded by RETRY_ATTEMPT_S, so a link that comes back after a long outage
        # carries states again within about a second: a SYN lost in the outage is sent afresh, not backed off)
        backoff = Backoff(first_s=0.2, max_s=RETRY_MAX_S)
        attempt_s = self.node.timeout_s
        while True:
            try:
                if not await self._connect_and_read(uri, attempt_s):
                    return  # refused for good (type mismatch or an error header): wait for the master to relist
                backoff.reset()
            except asyncio.IncompleteReadError:
                logger.debug("%s: publisher %s closed the connection", self.topic, uri)
            except (OSError, TimeoutError, CodecError) as exc:
                level = logging.INFO if backoff.at_first else logging.DEBUG
                msg = "%s: cannot read from publisher %s (%r); retrying in %.1f s"
                logger.log(level, msg, self.topic, uri, exc, backoff.delay_s)
            except Exception:  # a peer's bad input must not take the node (and its TaskGroup) down
                logger.exception(
                    "%s: connection to publisher %s failed; retrying in %.1f s", self.topic, uri, backoff.delay_s
                )
            attempt_s = min(self.node.timeout_s, RETRY_ATTEMPT_S)
            await backoff.sleep()

    async def _connect_and_read(self, uri: str, attempt_s: float) -> bool:
        node, ours = self.node, self.msg_type
        code, status, proto = await call_ros(
            uri, "requestTopic", node.name, self.topic, [["TCPROS"]], timeout_s=attempt_s
        )
        if code != 1 or not isinstance(proto, list) or len(proto) < 3 or proto[0] != "TCPROS":
            raise ConnectionRefusedError(f"requestTopic answered {code}, {status!r}, {proto!r}")
        loop = asyncio.get_running_loop()
        async with asyncio.timeout(attempt_s):
            transport, reader = await loop.create_connection(_tcpros.FrameReader, str(proto[1]), int(proto[2]))
        try:
            _tcpros.tune_socket(transport)
            transport.write(
                _tcpros.encode_header(
                    {
                        "callerid": node.name,
                        "topic": self.topic,
                        "md5sum": ours._md5sum,
                        "type": ours._type,
                        "message_definition": ours._full_text,
                        "tcp_nodelay": "1",
                    }
                )
            )
            async with asyncio.timeout(node.timeout_s):
                header = await reader.header()
            peer = f"publisher {header.get('callerid', uri)}"
            if "error" in header:
                await self._explain_refusal(proto[1], int(proto[2]), peer, header["error"])
                return False
            their_md5, their_type = header.get("md5sum", ""), header.get("type", "")
            if their_md5 not in ("*", ours._md5sum):
                logger.warning(_type_mismatch(self.topic, peer, their_type, their_md5, ours))
                return False
            conn = _PublisherConn(uri, header.get("callerid", ""))

            def on_frame(body: bytes) -> None:  # in the event loop's read callback: no task wakes per message
                conn.bytes += len(body) + 4
                conn.count += 1
                try:
                    msg = ours.deserialize(body)
                except CodecError as exc:
                    if _log_limit(f"decode {self.topic}"):
                        logger.warning("%s: dropped a message from %s: %s", self.topic, peer, exc)
                    return
                self._deliver(msg)

            self.connected[uri] = conn
            self.changed.notify()
            try:
                reader.start(on_frame)
                await reader.wait_closed()
            finally:
                del self.connected[uri]
                self.changed.notify()
        finally:
            transport.close()
        return True

    async def _explain_refusal(self, host: str, port: int, peer: str, error: str) -> None:
        """Log why a publisher refused us. rospy's error text may omit the md5s, so ask once more with md5 "*" (as
        rostopic does) to learn its type and md5, then hang up."""
        node, ours = self.node, self.msg_type
        theirs: dict[str, str] = {}
        try:
            async with asyncio.timeout(node.timeout_s):
                reader, writer = await asyncio.open_connection(host, port)
                try:
                    header = {"callerid": node.name, "topic": self.topic, "md5sum": "*", "type": "*"}
                    writer.write(_tcpros.encode_header(header))
                    theirs = await _tcpros.read_header(reader)
                finally:
                    writer.close()
        except (OSError, TimeoutError, asyncio.IncompleteReadError, CodecError) as exc:
            logger.debug("%s: could not ask %s for its type: %r", self.topic, peer, exc)
        their_md5 = theirs.get("md5sum", "")
        if "error" not in theirs and their_md5 and their_md5 != ours._md5sum:
            logger.warning(_type_mismatch(self.topic, peer, theirs.get("type", ""), their_md5, ours) + f" ({error})")
        else:
            logger.warning("%s: %s refused our subscription: %s", self.topic, peer, error)

    def _deliver(self, msg: Ros1Message) -> None:
        recv_ns = time.monotonic_ns()
        for handle in self.handles:
            handle._deliver(msg, recv_ns)

    def close(self) -> None:
        self.closed = True
        for task in self.links.values():
            task.cancel()
        self.links.clear()
        for handle in self.handles:
            handle._closed = True
            handle._arrived.notify()


class Ros1Subscriber(Generic[M]):
    """A subscription to a ROS 1 topic: keeps the newest message; ``receive`` waits for the next one.

    Attributes:
        topic: the topic name.
        msg_type: the message class.
        latest_recv_ns: ``time.monotonic_ns()`` when the newest message arrived (None before the first).
    """

    def __init__(self, sub: _Subscription, msg_type: type[M], callback: Callable[[M], None] | None) -> None:
        self.topic = sub.topic
        self.msg_type = msg_type
        self.latest_recv_ns: int | None = None
        self._sub = sub
        self._callback = callback
        self._latest: M | None = None
        self._count = 0  # messages delivered so far
        self._cursor: int | None = None  # _count at the previous receive()
        self._arrived = _Changed()
        self._closed = False

    def _deliver(self, msg: M, recv_ns: int) -> None:
        self._latest = msg
        self.latest_recv_ns = recv_ns
        self._count += 1
        self._arrived.notify()
        if self._callback is not None:
            try:
                self._callback(msg)
            except Exception:
                if _log_limit(f"callback {self.topic} {id(self)}"):
                    logger.exception("%s: the subscriber callback raised (logged at most every 5 s)", self.topic)

    def latest(self) -> M | None:
        """The newest message, or None before the first; never waits."""
        return self._latest

    async def receive(self, timeout_s: float | None = None) -> M:
        """The newest message that arrived after the previous ``receive`` (the first call: after the call).

        Messages that arrived in between and were superseded are skipped. Cancelling leaves nothing behind.

        Raises:
            TimeoutError: none within ``timeout_s`` (the message names the topic).
            TransportClosedError: the node was closed.
        """
        if self._cursor is None:
            self._cursor = self._count
        cursor = self._cursor
        await self._arrived.wait_until(
            lambda: self._count > cursor or self._closed,
            timeout_s,
            lambda: f"no message on {self.topic} ({self.msg_type._type})",
        )
        if self._count == cursor:
            raise TransportClosedError(f"{self.topic}: the ROS 1 node was closed")
        self._cursor = self._count
        assert self._latest is not None
        return self._latest

    @property
    def publisher_count(self) -> int:
        """Publishers with an open TCPROS connection to us."""
        return len(self._sub.connected)

    async def wait_for_publishers(self, n: int = 1, timeout_s: float = 10.0) -> None:
        """Wait until at least ``n`` publishers are connected.

        Raises:
            TimeoutError: fewer within ``timeout_s`` (names the topic and the count).
        """
        sub = self._sub
        await sub.changed.wait_until(
            lambda: len(sub.connected) >= n,
            timeout_s,
            lambda: f"{self.topic}: {len(sub.connected)} of {n} publishers connected",
        )


# ---------------------------------------------------------------------------------------------- publishing


class _SubscriberLink:
    """One subscriber's connection: a bounded queue of frames and the task that writes them.

    It remembers when each frame it wrote was published until the subscriber's kernel has acknowledged it
    (``SIOCOUTQ``), so ``oldest_undelivered_ns`` tells how long the oldest message still on its way has waited: in
    a partition the frames wait in the kernel's send queue, and TCP would deliver them, however old, when the link
    heals; ``abort`` discards them with a reset.
    """

    def __init__(self, pub: _Publication, callerid: str, writer: asyncio.StreamWriter) -> None:
        self.id = next(_conn_ids)
        self.pub = pub
        self.callerid = callerid
        self.writer = writer
        self.queue: collections.deque[tuple[int, bytes]] = collections.deque()  # (published ns, frame)
        self.unacked: collections.deque[tuple[int, int]] = collections.deque()  # (published ns, end in self.bytes)
        self.ready = asyncio.Event()
        self.bytes = 0
        self.count = 0
        self.dropped = 0
        self.aborted = False

    def put(self, frame: bytes) -> None:
        transport = self.writer.transport
        now = time.monotonic_ns()
        if not self.queue and not transport.is_closing() and transport.get_write_buffer_size() == 0:
            # nothing waits and the socket takes it: written now, in the publisher's frame (rospy's queue_size=None),
            # not one event-loop round later by the write task
            self._write(now, frame)
            return
        if len(self.queue) >= self.pub.queue_size:
            # A slow subscriber loses its oldest frames, so it neither blocks the others nor grows memory.
            self.queue.popleft()
            self.dropped += 1
            self.pub.dropped += 1
            if _log_limit(f"drop {self.pub.topic} {self.id}"):
                logger.warning(
                    "%s: subscriber %s is slow; dropped %d frames so far", self.pub.topic, self.callerid, self.dropped
                )
        self.queue.append((now, frame))
        self.ready.set()

    def _write(self, published_ns: int, frame: bytes) -> None:
        self.writer.write(frame)
        self.bytes += len(frame)
        self.count += 1
        if len(self.unacked) >= _MAX_UNACKED_FRAMES:
            self.unacked.pop()  # the newest entry's end moves on to this frame's: the oldest time is kept
        self.unacked.append((published_ns, self.bytes))

    def oldest_undelivered_ns(self) -> int | None:
        """When the oldest message not yet acknowledged by the subscriber's kernel was published (monotonic ns), or
        None when everything written has been acknowledged and nothing waits."""
        transport = self.writer.transport
        if transport.is_closing():
            return None
        try:
            in_kernel = _tcpros.unacked_bytes(transport)
        except OSError:
            return None
        acked = self.bytes - transport.get_write_buffer_size() - in_kernel
        unacked = self.unacked
        while unacked and unacked[0][1] <= acked:
            unacked.popleft()
        if unacked:
            return unacked[0][0]
        return self.queue[0][0] if self.queue else None

    def abort(self) -> None:
        """Reset the connection, discarding every frame not yet delivered; the subscriber reconnects."""
        self.aborted = True
        self.queue.clear()
        self.unacked.clear()
        _tcpros.abort(self.writer.transport)

    async def write_loop(self) -> None:
        try:
            while True:
                await self.ready.wait()
                self.ready.clear()
                while self.queue:
                    self._write(*self.queue.popleft())
                    await self.writer.drain()
        except OSError as exc:
            logger.debug("%s: subscriber %s went away (%r)", self.pub.topic, self.callerid, exc)
            self.writer.close()  # the connection task then sees EOF and removes the link


class _Publication:
    """Our publication of one topic: the subscriber links, the latched frame."""

    def __init__(self, node: Ros1Node, topic: str, msg_type: type[Ros1Message], latch: bool, queue_size: int):
        self.node = node
        self.topic = topic
        self.msg_type = msg_type
        self.latch = latch
        self.queue_size = queue_size
        self.links: set[_SubscriberLink] = set()
        self.last_frame: bytes | None = None
        self.handles = 0
        self.dropped = 0
        self.aborted = 0
        self.count = 0
        self.changed = _Changed()
        self.closed = False

    def publish(self, msg: Ros1Message) -> None:
        if self.closed:
            raise TransportClosedError(f"{self.topic}: the publisher or its ROS 1 node was closed")
        if not isinstance(msg, self.msg_type):
            raise CodecError(f"{self.topic}: expected {self.msg_type.__name__}, got {type(msg).__name__}")
        frame = _tcpros.frame(msg.serialize())
        self.count += 1
        if self.latch:
            self.last_frame = frame
        for link in self.links:
            link.put(frame)

    def abort_undelivered(self, published_before_ns: int | None) -> int:
        """Reset every subscriber connection still holding a message published before ``published_before_ns``
        (None: any message) that its subscriber has not acknowledged; how many were reset."""
        aborted = 0
        for link in list(self.links):
            oldest = link.oldest_undelivered_ns()
            if oldest is not None and (published_before_ns is None or oldest < published_before_ns):
                logger.warning(
                    "%s: reset the connection to subscriber %s: a message published %.2f s ago is still undelivered",
                    self.topic,
                    link.callerid,
                    (time.monotonic_ns() - oldest) / 1e9,
                )
                link.abort()
                self.links.discard(link)
                aborted += 1
        if aborted:
            self.aborted += aborted
            self.changed.notify()
        return aborted

    def header(self) -> dict[str, str]:
        return {
            "callerid": self.node.name,
            "topic": self.topic,
            "md5sum": self.msg_type._md5sum,
            "type": self.msg_type._type,
            "message_definition": self.msg_type._full_text,
            "latching": "1" if self.latch else "0",
        }

    async def serve(self, callerid: str, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Run one subscriber's connection after its header was accepted, until either side closes it."""
        link = _SubscriberLink(self, callerid, writer)
        if self.latch and self.last_frame is not None:
            link.put(self.last_frame)  # counted from now: the latched message is sent again, as published now
        self.links.add(link)
        self.changed.notify()
        writer_task = self.node._spawn(link.write_loop(), name=f"ros1 pub {self.topic} -> {callerid}")
        try:
            while await reader.read(4096):  # subscribers send nothing after their header; this waits for EOF
                pass
        except OSError:
            pass
        finally:
            writer_task.cancel()
            self.links.discard(link)
            self.changed.notify()

    def close(self) -> None:
        self.closed = True
        for link in self.links:
            link.writer.close()


class Ros1Publisher(Generic[M]):
    """A publication of a ROS 1 topic. ``publish`` never waits.

    Attributes:
        topic: the topic name.
        msg_type: the message class.
    """

    def __init__(self, pub: _Publication, msg_type: type[M]) -> None:
        self.topic = pub.topic
        self.msg_type = msg_type
        self._pub = pub

    def publish(self, msg: M) -> None:
        """Serialize ``msg`` once and queue it for every connected subscriber (and as the latched message).

        A subscriber whose queue is full loses its oldest frame (counted in ``dropped_frames``).

        Raises:
            CodecError: ``msg`` is not a ``msg_type`` or a field cannot be encoded.
            TransportClosedError: the node was closed.
        """
        self._pub.publish(msg)

    @property
    def subscriber_count(self) -> int:
        """Subscribers with an open TCPROS connection to us."""
        return len(self._pub.links)

    @property
    def dropped_frames(self) -> int:
        """Frames dropped so far for slow subscribers (over all of them)."""
        return self._pub.dropped

    @property
    def aborted_connections(self) -> int:
        """Subscriber connections reset so far by ``abort_undelivered``."""
        return self._pub.aborted

    def oldest_undelivered_age_s(self) -> float | None:
        """How long ago the oldest message that some subscriber's kernel has not acknowledged yet was published, or
        None when every subscriber has acknowledged everything."""
        oldest = [t for link in self._pub.links if (t := link.oldest_undelivered_ns()) is not None]
        return (time.monotonic_ns() - min(oldest)) / 1e9 if oldest else None

    def abort_undelivered(self, max_age_s: float | None = None) -> int:
        """Reset (TCP RST, ``SO_LINGER`` 0) every subscriber connection that still holds a message published more
        than ``max_age_s`` ago (None: any message) and not yet acknowledged by the subscriber's kernel, discarding
        what it holds; returns how many were reset.

        TCP delivers whatever waits in a connection's send queue when a broken link heals, however old: a command
        without a stamp would then move an arm on a stale plan. The subscriber learns of the reset only when its
        next segment (a keepalive probe: rospy's after 60 s idle) is answered with another; ``Ros1Bridge`` offers
        its commands from a new node instead, which subscribers connect to at once.
        """
        before = None if max_age_s is None else time.monotonic_ns() - round(max_age_s * 1e9)
        return self._pub.abort_undelivered(before)

    async def wait_for_subscribers(self, n: int = 1, timeout_s: float = 10.0) -> None:
        """Wait until at least ``n`` subscribers are connected.

        Raises:
            TimeoutError: fewer within ``timeout_s`` (names the topic and the count).
        """
        pub = self._pub
        await pub.changed.wait_until(
            lambda: len(pub.links) >= n,
            timeout_s,
            lambda: f"{self.topic}: {len(pub.links)} of {n} subscribers connected",
        )
