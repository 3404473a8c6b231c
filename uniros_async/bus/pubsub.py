"""Publishers and subscriptions (see node.py for how connections are chosen and QoS applied)."""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Callable
from typing import TYPE_CHECKING, Any, Generic, TypeVar

import numpy as np

from uniros_async.backoff import Backoff
from uniros_async.bus import codec
from uniros_async.bus._loan import HEAD_BYTES, Loan, check_message, encode_head
from uniros_async.bus._local import (
    _HELLO_TIMEOUT_S,
    _LOCAL_PUBS,
    _LOCAL_SUBS,
    PROCESS_TOKEN,
    _maybe_await,
)
from uniros_async.bus.qos import QoS
from uniros_async.errors import (
    AuthenticationError,
    CodecError,
    ConfigError,
    DomainError,
    FrameTooLargeError,
    TransportBrokenError,
    TransportClosedError,
    TransportError,
)
from uniros_async.transports.base import Transport

if TYPE_CHECKING:
    from uniros_async.bus.node import Node

logger = logging.getLogger(__name__)

M = TypeVar("M")
Req = TypeVar("Req")
Resp = TypeVar("Resp")


LATEST_POLL_S = (0.001, 0.05)
"""How often a ``latest`` sink whose link is backed up looks again whether its last frame has left (the first wait,
doubling up to the last)."""


class _Sink:
    """One remote subscriber of a publisher: a bounded queue of encoded frames and the task that sends them.

    A ``latest`` sink sends a frame only once the one before it has left this host (``Transport.unsent_bytes``),
    and meanwhile keeps only the newest: on a link slower than the topic the subscriber gets fresh messages at the
    rate the link carries, not every message ever later out of a send buffer that grows without bound.
    """

    def __init__(self, conn: Transport, qos: QoS) -> None:
        self.conn = conn
        self.queue: collections.deque[list[bytes | memoryview]] = collections.deque(maxlen=qos.depth)
        self.wake = asyncio.Event()
        self.dropped = 0
        self.qos = qos
        self.busy = asyncio.Lock()  # held while a frame is sent, and through a loan of this connection's ring

    def push(self, frame: list[bytes | memoryview]) -> None:
        if len(self.queue) == self.queue.maxlen:
            self.dropped += 1
        self.queue.append(frame)
        self.wake.set()

    async def run(self) -> None:
        latest = self.qos.kind == "latest"
        while True:
            await self.wake.wait()
            self.wake.clear()
            async with self.busy:
                while self.queue:
                    await self.conn.send(self.queue.popleft())
                    if latest and self.conn.unsent_bytes():
                        await self._until_sent()

    async def _until_sent(self) -> None:
        """Wait until the last frame has left this host (polled: no event says so; 0 also once the connection has
        ended, which ends this wait, and the subscriber going away cancels it)."""
        poll_s, cap_s = LATEST_POLL_S
        while self.conn.unsent_bytes():
            await asyncio.sleep(poll_s)
            poll_s = min(2 * poll_s, cap_s)


class Publisher(Generic[M]):
    """Publishes ``msg_type`` messages on ``topic``. Create with ``await node.create_publisher(...)``."""

    def __init__(self, node: Node, msg_type: type[M], topic: str, qos: QoS) -> None:
        self.node = node
        self.msg_type = msg_type
        self.topic = topic
        self.qos = qos
        self._local = _LOCAL_SUBS[(node.domain_id, topic)]
        self._sinks: list[_Sink] = []
        self.published = 0
        self.loaned_in_place = 0
        """Messages published from a loan written in place in a subscriber's ring (no copy after the producer's)."""
        self._closed = False
        self._subs_changed = asyncio.Event()

    def publish(self, msg: M) -> None:
        """Deliver ``msg`` to every subscriber; never waits. Do not mutate ``msg``'s arrays afterwards.

        Raises:
            CodecError: ``msg`` is not a ``msg_type``.
            TransportClosedError: the publisher (or its node) was closed.
        """
        if self._closed:
            raise TransportClosedError(f"publisher of {self.topic} is closed")
        if type(msg) is not self.msg_type:
            raise CodecError(f"{self.topic}: expected {self.msg_type.__name__}, got {type(msg).__name__}")
        self.published += 1
        for sub in self._local:
            sub._deliver(msg)
        if self._sinks:
            frame = codec.encode(msg)
            for sink in self._sinks:
                sink.push(frame)

    @contextlib.asynccontextmanager
    async def loan(self, shape: tuple[int, ...], dtype: Any = np.uint8) -> AsyncIterator[Loan[M]]:
        """Loan a message's array: write it in the block, set ``loan.message``, and it is published when the block
        ends (not if the block raises). Shaped like rclcpp's ``borrow_loaned_message`` and iceoryx's ``loan``.

        With one remote subscriber over shm and none in this process, ``loan.array`` is the frame's own place in
        that subscriber's ring: the producer's write is the frame's only copy on this side. Otherwise it is a
        buffer of the publisher's own, published as ``publish`` would (one copy per remote subscriber, made by its
        transport; in-process subscribers get the message). May wait for room in the ring, as a send does.
        Don't use ``loan.array`` after the block. The other frames of this publisher wait for the block to end.

        Example::

            async with pub.loan((480, 640, 3)) as loan:
                renderer.render_into(loan.array)
                loan.message = Image(header=Header(stamp_ns=t), data=loan.array)

        Raises:
            TransportClosedError: the publisher (or its node) was closed.
            CodecError: at the block's end, ``loan.message`` is unset, not a ``msg_type``, or holds an array other
                than the loan's (nothing is published).
        """
        if self._closed:
            raise TransportClosedError(f"publisher of {self.topic} is closed")
        dt = np.dtype(dtype)
        count = 1
        for s in shape:
            count *= int(s)
        nbytes = HEAD_BYTES + count * dt.itemsize
        sink = self._sinks[0] if len(self._sinks) == 1 and not self._local else None
        lends: Callable[[int], bool] | None = getattr(sink.conn, "lends", None) if sink is not None else None
        if sink is None or lends is None or not lends(nbytes):  # no ring to lend: a buffer of our own
            loan: Loan[M] = Loan(np.empty(shape, dt), in_place=False)
            yield loan
            self.publish(check_message(self.topic, self.msg_type, loan))
            return
        async with contextlib.AsyncExitStack() as stack:
            await stack.enter_async_context(sink.busy)
            buf: memoryview | None = None
            try:
                if sink.qos.kind == "latest":
                    sink.dropped += len(sink.queue)
                    sink.queue.clear()
                while sink.queue:
                    await sink.conn.send(sink.queue.popleft())
                buf = await stack.enter_async_context(sink.conn.loan(nbytes))
            except (TransportBrokenError, TransportClosedError, FrameTooLargeError) as exc:
                logger.debug("%s: no loan from the subscriber's ring (%s): a buffer of our own", self.topic, exc)
            if buf is None:
                loan = Loan(np.empty(shape, dt), in_place=False)
                yield loan
                self.publish(check_message(self.topic, self.msg_type, loan))
                return
            loan = Loan(np.frombuffer(buf, dt, count, HEAD_BYTES).reshape(shape), in_place=True)
            yield loan
            msg = check_message(self.topic, self.msg_type, loan)
            head = encode_head(msg)
            buf[: len(head)] = head
            self.published += 1
            self.loaned_in_place += 1
            try:
                await stack.aclose()  # ShmTransport.loan's end: the frame is committed to the ring
            except (TransportBrokenError, TransportClosedError) as exc:
                # the subscriber went away as the frame was sent: its sink's task sees it too and removes it
                logger.debug("%s: loaned frame to a subscriber that went away: %s", self.topic, exc)

    @property
    def subscription_count(self) -> int:
        """Subscribers currently connected (in-process and remote)."""
        return len(self._local) + len(self._sinks)

    @property
    def dropped(self) -> int:
        """Frames dropped from full outgoing queues (QoS), over all remote subscribers."""
        return sum(s.dropped for s in self._sinks)

    async def wait_for_subscribers(self, n: int = 1, timeout_s: float = 5.0) -> None:
        """Wait until at least ``n`` subscribers are connected.

        Raises:
            TimeoutError: fewer than ``n`` after ``timeout_s`` (the count is in the message).
        """
        try:
            async with asyncio.timeout(timeout_s):
                while self.subscription_count < n:
                    self._subs_changed.clear()
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(0.05):  # in-process subscribers do not signal
                            await self._subs_changed.wait()
        except TimeoutError:
            raise TimeoutError(
                f"{self.topic}: {self.subscription_count} subscriber(s) after {timeout_s} s, expected {n}"
            ) from None

    async def _serve_sink(self, conn: Transport, qos: QoS) -> None:
        sink = _Sink(conn, qos)
        self._sinks.append(sink)
        self._subs_changed.set()
        try:
            async with asyncio.TaskGroup() as tg:
                sender = tg.create_task(sink.run())
                # The subscriber sends nothing after its hello: a receive returns only when it goes away.
                with contextlib.suppress(TransportBrokenError, TransportClosedError):
                    await conn.receive()
                sender.cancel()
        except* (TransportBrokenError, TransportClosedError):
            pass
        finally:
            self._sinks.remove(sink)
            self._subs_changed.set()
            await conn.aclose()

    async def aclose(self) -> None:
        """Stop publishing; remote subscribers see the connection close. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self.node._publishers.remove(self)
        _LOCAL_PUBS[(self.node.domain_id, self.topic)].remove(self)
        for sink in list(self._sinks):
            await sink.conn.aclose()
        with contextlib.suppress(DomainError):
            await self.node._registry.request("unadvertise", topic=self.topic, node=self.node.name)


class Subscription(Generic[M]):
    """Receives ``msg_type`` messages of ``topic``.

    Three ways to read: a callback (given at creation), ``async for msg in sub``, or ``sub.latest()`` which
    returns the newest message at once without waiting (None before the first). ``received`` counts arrivals,
    ``dropped`` those pushed out of the bounded queue (QoS), ``rejected`` malformed frames from peers.
    """

    def __init__(
        self,
        node: Node,
        msg_type: type[M],
        topic: str,
        qos: QoS,
        callback: Callable[[M], Any] | None,
        zero_copy: bool,
    ) -> None:
        self.node = node
        self.msg_type = msg_type
        self.topic = topic
        self.qos = qos
        self.callback = callback
        self.zero_copy = zero_copy
        self._queue: collections.deque[M] = collections.deque(maxlen=qos.depth)
        self._wake = asyncio.Event()
        self._latest: M | None = None
        self.latest_recv_ns = 0
        self.received = 0
        self.dropped = 0
        self.rejected = 0
        self._readers: dict[str, asyncio.Task[None]] = {}
        self._connected: set[str] = set()  # keys of the remote publishers a reader is connected to now
        self._closed = False
        self._pub_count_changed = asyncio.Event()

    def latest(self) -> M | None:
        """The newest message received, or None; never waits."""
        return self._latest

    def _deliver(self, msg: M) -> None:
        self._latest = msg
        self.latest_recv_ns = time.monotonic_ns()
        self.received += 1
        if self.zero_copy:
            return
        if len(self._queue) == self._queue.maxlen and self.qos.kind == "reliable":
            self.dropped += 1
        self._queue.append(msg)
        self._wake.set()

    async def receive(self) -> M:
        """Wait for the next message (per QoS: with ``latest`` the newest unread one).

        Raises:
            TransportClosedError: the subscription was closed.
        """
        while not self._queue:
            if self._closed:
                raise TransportClosedError(f"subscription to {self.topic} is closed")
            self._wake.clear()
            await self._wake.wait()
        return self._queue.popleft()

    def __aiter__(self) -> AsyncIterator[M]:
        return self

    async def __anext__(self) -> M:
        try:
            return await self.receive()
        except TransportClosedError:
            raise StopAsyncIteration from None

    @property
    def publisher_count(self) -> int:
        """Publishers this subscription is connected to (in-process and remote)."""
        local = len(_LOCAL_PUBS.get((self.node.domain_id, self.topic), ())) if self.node._allows_memory else 0
        return local + len(self._connected)

    async def wait_for_publishers(self, n: int = 1, timeout_s: float = 5.0) -> None:
        """Wait until connected to at least ``n`` publishers.

        Raises:
            TimeoutError: fewer after ``timeout_s``.
        """
        try:
            async with asyncio.timeout(timeout_s):
                while self.publisher_count < n:
                    self._pub_count_changed.clear()
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(0.05):
                            await self._pub_count_changed.wait()
        except TimeoutError:
            raise TimeoutError(
                f"{self.topic}: connected to {self.publisher_count} publisher(s) after {timeout_s} s, expected {n}"
            ) from None

    # ---- remote publishers

    def _update_publishers(self, publishers: list[dict[str, Any]], *, restart: bool = False) -> None:
        """Read from exactly ``publishers`` (the registry's list). ``restart``: the registry was reached again, so
        the link may be back: a reader still waiting to reconnect (backed off, or in an attempt whose SYN was lost)
        starts again at once."""
        wanted = {}
        for info in publishers:
            if info["token"] == PROCESS_TOKEN and self.node._allows_memory:
                continue  # delivered in-process
            wanted[f"{info['token']}/{info['node']}"] = info
        for key in list(self._readers):
            if key not in wanted:
                self._readers.pop(key).cancel()
        for key, info in wanted.items():
            if restart and key in self._readers and key not in self._connected:
                self._readers.pop(key).cancel()
            if key not in self._readers or self._readers[key].done():
                self._readers[key] = self.node._start(self._read_from(key, info), name=f"sub {self.topic} <- {key}")

    async def _read_from(self, key: str, info: dict[str, Any]) -> None:
        backoff = Backoff(first_s=0.01, max_s=1.0)
        while True:
            conn: Transport | None = None
            try:
                try:
                    conn = await self.node._connect_to(info)
                except ConfigError as exc:  # no endpoint this node may use (tcp only, in a tls domain): no retry
                    self.node._log.warning("%s: cannot subscribe to %s: %s", self.topic, info["node"], exc)
                    return
                await conn.send(
                    codec.encode_plain(
                        {
                            "op": "subscribe",
                            "topic": self.topic,
                            "type": self.msg_type.__name__,
                            "qos": self.qos.to_wire(),
                        }
                    )
                )
                async with asyncio.timeout(_HELLO_TIMEOUT_S):
                    reply = codec.decode_plain(await conn.receive())
                if not reply.get("ok"):
                    logger.error(
                        "%s: publisher %s refused the subscription: %s", self.topic, info["node"], reply.get("error")
                    )
                    return
                self._connected.add(key)
                self._pub_count_changed.set()
                backoff.reset()
                expected = self.msg_type
                while True:
                    frame = await conn.receive()
                    try:
                        msg = codec.decode(frame if self.zero_copy else bytes(frame), expected)
                    except CodecError as exc:
                        self.rejected += 1
                        if self.rejected < 10 or self.rejected % 1000 == 0:
                            logger.warning(
                                "%s: rejected frame %d from %s: %s", self.topic, self.rejected, info["node"], exc
                            )
                        continue
                    self._deliver(msg)
                    if self.zero_copy and self.callback is not None:
                        r = _maybe_await(self.callback(msg))
                        if r is not None:
                            await r
            except AuthenticationError as exc:  # a key that differs; a tls certificate not naming the address dialled
                msg = "%s: refused publisher %s (%s); retrying in %.2f s"
                self.node._log.warning(msg, self.topic, info["node"], exc, backoff.delay_s)
            except (TransportError, TimeoutError, OSError, CodecError) as exc:
                msg = "%s: connection to %s lost (%s); retrying in %.2f s"
                logger.debug(msg, self.topic, info["node"], exc, backoff.delay_s)
            finally:
                self._connected.discard(key)
                self._pub_count_changed.set()
                if conn is not None:
                    await conn.aclose()
            await backoff.sleep()

    async def _dispatch(self) -> None:
        assert self.callback is not None
        cb = self.callback
        while True:
            try:
                msg = await self.receive()
            except TransportClosedError:
                return
            r = _maybe_await(cb(msg))
            if r is not None:
                await r

    async def aclose(self) -> None:
        """Stop receiving; idempotent. A task blocked in ``receive`` gets TransportClosedError."""
        if self._closed:
            return
        self._closed = True
        self._wake.set()
        with contextlib.suppress(ValueError):
            _LOCAL_SUBS[(self.node.domain_id, self.topic)].remove(self)
        for t in self._readers.values():
            t.cancel()
        self.node._subscriptions.remove(self)
        with contextlib.suppress(DomainError):
            await self.node._registry.request("unsubscribe", topic=self.topic, node=self.node.name)
