"""Nodes, publishers, subscriptions, timers, services and parameters.

A node joins a domain (``open_node("name", domain=uri)``); everything it creates is named relative to its
namespace (``"joint_states"`` in namespace ``/rx200_1`` is ``/rx200_1/joint_states``; ``"/clock"`` is absolute;
``"~/status"`` is under the node's own name). The transport of a topic connection is chosen per connection:

- same process (and same domain): no transport at all, the subscriber gets the message object itself;
- same machine: ``shm://`` (shared-memory rings), unless the node asked for ``transport="tcp"``;
- otherwise ``tcp://``.

Publishing never blocks: ``publish`` hands the message to in-process subscribers and the encoded frame (encoded
once, however many remote subscribers) to one bounded queue per remote subscriber, which a sender task drains.
What the queues keep when full is the topic's QoS (``latest`` or ``reliable(depth)``, see qos.py).

Every task a node starts belongs to the node's TaskGroup; leaving ``async with open_node(...)`` cancels them and
closes every connection. A timer or subscription callback that raises ends the node with that error (a bug
should not be hidden); a malformed frame from a peer is counted in ``rejected`` and logged, never fatal.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import inspect
import itertools
import logging
import os
import socket
import time
import traceback
import uuid
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any, Generic, TypeVar

from uniros_async.bus import codec
from uniros_async.bus.domain import Domain
from uniros_async.bus.qos import QoS, latest
from uniros_async.bus.tasks import unwrap_task_group
from uniros_async.clock import Clock, wall_clock
from uniros_async.config import load_yaml
from uniros_async.errors import (
    CodecError,
    ConfigError,
    DomainError,
    NameConflictError,
    ServiceError,
    TransportBrokenError,
    TransportClosedError,
    TransportError,
)
from uniros_async.transports.base import Listener, Transport, TransportOptions, connect, listen

__all__ = ["Node", "Publisher", "Service", "ServiceClient", "Subscription", "Timer", "open_node"]

logger = logging.getLogger(__name__)

M = TypeVar("M")
Req = TypeVar("Req")
Resp = TypeVar("Resp")

PROCESS_TOKEN = uuid.uuid4().hex
"""Identifies this process to the registry (pids are reused; tokens are not)."""


def _host_id() -> str:
    try:
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        boot = ""
    return f"{socket.gethostname()}:{boot}"


HOST_ID = _host_id()
TRANSPORT_CHOICES = ("auto", "memory", "shm", "tcp")

# In-process delivery tables, keyed by (domain_id, topic). Only subscriptions that accept in-process delivery
# (their node's transport is "auto" or "memory") are listed.
_LOCAL_SUBS: dict[tuple[str, str], list[Subscription[Any]]] = collections.defaultdict(list)
_LOCAL_PUBS: dict[tuple[str, str], list[Publisher[Any]]] = collections.defaultdict(list)
_LOCAL_SERVICES: dict[tuple[str, str], Service[Any, Any]] = {}

_HELLO_TIMEOUT_S = 5.0


def _maybe_await(result: Any) -> Awaitable[Any] | None:
    return result if inspect.isawaitable(result) else None


# ================================================================================================== registry client


class _RegistryClient:
    """This node's connection to its domain registry: requests with ids, and pushed notifications."""

    def __init__(self, conn: Transport, timeout_s: float, on_notify: Callable[[dict[str, Any]], None]) -> None:
        self._conn = conn
        self._timeout_s = timeout_s
        self._ids = itertools.count(1)
        self._waiting: dict[int, asyncio.Future[Any]] = {}
        self._on_notify = on_notify
        self._lock = asyncio.Lock()
        self.closed = False

    async def run(self) -> None:
        try:
            while True:
                msg = codec.decode_plain(await self._conn.receive())
                rid = msg.get("id")
                if rid is None:
                    self._on_notify(msg)
                    continue
                fut = self._waiting.pop(rid, None)
                if fut is not None and not fut.done():
                    fut.set_result(msg)
        except (TransportBrokenError, TransportClosedError, CodecError) as exc:
            self.closed = True
            for fut in self._waiting.values():
                if not fut.done():
                    fut.set_exception(DomainError(f"lost the connection to the domain registry: {exc}"))
            self._waiting.clear()
            if not isinstance(exc, TransportClosedError):
                logger.error("lost the connection to the domain registry at %s: %s", self._conn.peer, exc)

    async def request(self, op: str, **kw: Any) -> Any:
        if self.closed:
            raise DomainError("the connection to the domain registry is closed")
        rid = next(self._ids)
        fut: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._waiting[rid] = fut
        try:
            async with asyncio.timeout(self._timeout_s):
                async with self._lock:
                    await self._conn.send(codec.encode_plain({"op": op, "id": rid, **kw}))
                reply = await fut
        except TimeoutError:
            raise DomainError(f"the domain registry did not answer {op!r} within {self._timeout_s} s") from None
        except TransportError as exc:
            raise DomainError(f"cannot reach the domain registry: {exc}") from exc
        finally:
            self._waiting.pop(rid, None)
        if not reply.get("ok"):
            kind, err = reply.get("kind"), reply.get("error", "")
            if kind == "name_conflict":
                raise NameConflictError(err)
            raise DomainError(err)
        return reply.get("result")


# ================================================================================================== publisher


class _Sink:
    """One remote subscriber of a publisher: a bounded queue of encoded frames and the task that sends them."""

    def __init__(self, conn: Transport, qos: QoS) -> None:
        self.conn = conn
        self.queue: collections.deque[list[bytes | memoryview]] = collections.deque(maxlen=qos.depth)
        self.wake = asyncio.Event()
        self.dropped = 0
        self.qos = qos

    def push(self, frame: list[bytes | memoryview]) -> None:
        if len(self.queue) == self.queue.maxlen:
            self.dropped += 1
        self.queue.append(frame)
        self.wake.set()

    async def run(self) -> None:
        while True:
            await self.wake.wait()
            self.wake.clear()
            while self.queue:
                await self.conn.send(self.queue.popleft())


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


# ================================================================================================== subscription


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
        return local + sum(1 for t in self._readers.values() if not t.done() and getattr(t, "connected", False))

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

    def _update_publishers(self, publishers: list[dict[str, Any]]) -> None:
        wanted = {}
        for info in publishers:
            if info["token"] == PROCESS_TOKEN and self.node._allows_memory:
                continue  # delivered in-process
            wanted[f"{info['token']}/{info['node']}"] = info
        for key in list(self._readers):
            if key not in wanted:
                self._readers.pop(key).cancel()
        for key, info in wanted.items():
            if key not in self._readers or self._readers[key].done():
                self._readers[key] = self.node._start(self._read_from(info), name=f"sub {self.topic} <- {key}")

    async def _read_from(self, info: dict[str, Any]) -> None:
        task = asyncio.current_task()
        delay = 0.01
        while True:
            conn: Transport | None = None
            try:
                conn = await self.node._connect_to(info)
                await conn.send(
                    codec.encode_plain(
                        {"op": "subscribe", "topic": self.topic, "type": self.msg_type.__name__, "qos": self.qos.to_wire()}
                    )
                )
                async with asyncio.timeout(_HELLO_TIMEOUT_S):
                    reply = codec.decode_plain(await conn.receive())
                if not reply.get("ok"):
                    logger.error("%s: publisher %s refused the subscription: %s", self.topic, info["node"], reply.get("error"))
                    return
                task.connected = True
                self._pub_count_changed.set()
                delay = 0.01
                expected = self.msg_type
                while True:
                    frame = await conn.receive()
                    try:
                        msg = codec.decode(frame if self.zero_copy else bytes(frame), expected)
                    except CodecError as exc:
                        self.rejected += 1
                        if self.rejected < 10 or self.rejected % 1000 == 0:
                            logger.warning("%s: rejected frame %d from %s: %s", self.topic, self.rejected, info["node"], exc)
                        continue
                    self._deliver(msg)
                    if self.zero_copy and self.callback is not None:
                        r = _maybe_await(self.callback(msg))
                        if r is not None:
                            await r
            except (TransportError, TimeoutError, OSError, CodecError) as exc:
                logger.debug("%s: connection to %s lost (%s); retrying in %.2f s", self.topic, info["node"], exc, delay)
            finally:
                task.connected = False
                self._pub_count_changed.set()
                if conn is not None:
                    await conn.aclose()
            await asyncio.sleep(delay)  # reconnect backoff (wall time: it is about sockets, not the domain clock)
            delay = min(delay * 2, 1.0)

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


# ================================================================================================== timer


class Timer:
    """Calls ``callback`` every ``period_s`` of the node's clock, at absolute deadlines (``next += period``).

    ``fire_times_ns`` keeps the last ``history`` actual fire times; ``overruns`` counts deadlines missed because
    the previous callback (or the machine) ran late; missed deadlines are skipped, never fired in a burst.
    """

    def __init__(self, node: Node, period_s: float, callback: Callable[[], Any], history: int) -> None:
        if period_s <= 0:
            raise ConfigError(f"timer period_s must be > 0, got {period_s}")
        self.node = node
        self.period_ns = round(period_s * 1e9)
        self.callback = callback
        self.fire_times_ns: collections.deque[int] = collections.deque(maxlen=history)
        self.deadlines_ns: collections.deque[int] = collections.deque(maxlen=history)
        self.overruns = 0
        self.fired = 0
        self._task: asyncio.Task[None] | None = None

    @property
    def period_s(self) -> float:
        return self.period_ns / 1e9

    async def _run(self, start_ns: int | None) -> None:
        clock = self.node.clock
        nxt = start_ns if start_ns is not None else clock.now_ns() + self.period_ns
        cb = self.callback
        while True:
            await clock.sleep_until(nxt)
            now = clock.now_ns()
            self.fire_times_ns.append(now)
            self.deadlines_ns.append(nxt)
            self.fired += 1
            r = _maybe_await(cb())
            if r is not None:
                await r
            nxt += self.period_ns
            now = clock.now_ns()
            if now >= nxt:
                missed = (now - nxt) // self.period_ns + 1
                self.overruns += missed
                nxt += missed * self.period_ns

    def cancel(self) -> None:
        """Stop firing."""
        if self._task is not None:
            self._task.cancel()


# ================================================================================================== services


class Service(Generic[Req, Resp]):
    """Answers ``Req`` with ``Resp`` by calling ``handler`` (sync or async)."""

    def __init__(self, node: Node, req_type: type[Req], resp_type: type[Resp], name: str, handler: Callable[[Req], Any]):
        self.node = node
        self.req_type = req_type
        self.resp_type = resp_type
        self.name = name
        self.handler = handler
        self.calls = 0
        self.failures = 0

    async def _invoke(self, req: Req) -> Resp:
        self.calls += 1
        try:
            resp = self.handler(req)
            if inspect.isawaitable(resp):
                resp = await resp
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            self.failures += 1
            raise ServiceError(
                f"service {self.name} failed: {type(exc).__name__}: {exc}", remote_traceback=traceback.format_exc()
            ) from exc
        if type(resp) is not self.resp_type:
            self.failures += 1
            raise ServiceError(f"service {self.name}: handler returned {type(resp).__name__}, expected {self.resp_type.__name__}")
        return resp  # type: ignore[no-any-return]

    async def _serve_conn(self, conn: Transport) -> None:
        try:
            while True:
                frame = await conn.receive()
                try:
                    req = codec.decode(bytes(frame), self.req_type)
                    resp = await self._invoke(req)
                except (CodecError, ServiceError) as exc:
                    tb = getattr(exc, "remote_traceback", "")
                    await conn.send(codec.encode_plain({"ok": False, "error": str(exc), "traceback": tb}))
                    continue
                await conn.send(codec.encode_plain({"ok": True}))
                await conn.send(codec.encode(resp))
        except (TransportBrokenError, TransportClosedError):
            pass
        finally:
            await conn.aclose()


class ServiceClient(Generic[Req, Resp]):
    """Calls a service by name: ``resp = await client.call(req, timeout_s=2.0)``."""

    def __init__(self, node: Node, req_type: type[Req], resp_type: type[Resp], name: str) -> None:
        self.node = node
        self.req_type = req_type
        self.resp_type = resp_type
        self.name = name
        self._conn: Transport | None = None
        self._lock = asyncio.Lock()

    async def call(self, req: Req, timeout_s: float = 5.0) -> Resp:
        """Call the service and wait for its response.

        Raises:
            TimeoutError: no response within ``timeout_s`` (the connection is dropped; the next call reconnects).
            DomainError: no such service in the domain.
            ServiceError: the handler raised; ``remote_traceback`` has the server's traceback.
        """
        if type(req) is not self.req_type:
            raise CodecError(f"service {self.name}: expected request {self.req_type.__name__}, got {type(req).__name__}")
        try:
            async with asyncio.timeout(timeout_s):
                local = _LOCAL_SERVICES.get((self.node.domain_id, self.name))
                if local is not None and self.node._allows_memory:
                    return await local._invoke(req)  # type: ignore[no-any-return]
                async with self._lock:
                    return await self._call_remote(req)
        except TimeoutError:
            await self._drop()
            raise TimeoutError(f"service {self.name} did not answer within {timeout_s} s") from None

    async def _call_remote(self, req: Req) -> Resp:
        for attempt in (0, 1):
            if self._conn is None:
                info = await self.node._registry.request("lookup_service", name=self.name)
                conn = await self.node._connect_to(info)
                await conn.send(codec.encode_plain({"op": "call", "service": self.name}))
                self._conn = conn
            try:
                await self._conn.send(codec.encode(req))
                head = codec.decode_plain(await self._conn.receive())
                if not head.get("ok"):
                    raise ServiceError(head.get("error", "service failed"), remote_traceback=head.get("traceback", ""))
                return codec.decode(bytes(await self._conn.receive()), self.resp_type)  # type: ignore[no-any-return]
            except (TransportBrokenError, TransportClosedError):
                await self._drop()
                if attempt:
                    raise
        raise AssertionError("unreachable")

    async def _drop(self) -> None:
        if self._conn is not None:
            conn, self._conn = self._conn, None
            await conn.aclose()

    async def aclose(self) -> None:
        """Close the connection to the server (the node closes its clients too); idempotent."""
        await self._drop()
        with contextlib.suppress(ValueError):
            self.node._clients.remove(self)

    async def wait_for_service(self, timeout_s: float = 5.0) -> None:
        """Wait until the service is advertised in the domain.

        Raises:
            TimeoutError: not advertised within ``timeout_s``.
        """
        try:
            async with asyncio.timeout(timeout_s):
                while True:
                    try:
                        await self.node._registry.request("lookup_service", name=self.name)
                        return
                    except DomainError:
                        await asyncio.sleep(0.02)
        except TimeoutError:
            raise TimeoutError(f"service {self.name} not advertised within {timeout_s} s") from None


# ================================================================================================== node


def _join(*parts: str) -> str:
    out = "/".join(p.strip("/") for p in parts if p.strip("/"))
    return "/" + out


class Node:
    """A participant in a domain. Create with ``async with open_node("name", domain=uri) as node:``."""

    def __init__(
        self,
        name: str,
        namespace: str,
        clock: Clock,
        transport: str,
        options: TransportOptions,
    ) -> None:
        if not name or "/" in name:
            raise ConfigError(f"node name must be a non-empty word without '/', got {name!r}")
        if transport not in TRANSPORT_CHOICES:
            raise ConfigError(f"transport must be one of {TRANSPORT_CHOICES}, got {transport!r}")
        self.namespace = _join(namespace) if namespace.strip("/") else ""
        self.name = _join(self.namespace, name)
        self.clock = clock
        self.transport = transport
        self.options = options
        self._tg: asyncio.TaskGroup = None  # type: ignore[assignment]  # set by open_node
        self._tasks: set[asyncio.Task[Any]] = set()
        self._registry: _RegistryClient = None  # type: ignore[assignment]
        self.domain_id = ""
        self.domain_uri = ""
        self._listeners: dict[str, Listener] = {}
        self._publishers: list[Publisher[Any]] = []
        self._subscriptions: list[Subscription[Any]] = []
        self._services: dict[str, Service[Any, Any]] = {}
        self._timers: list[Timer] = []
        self._clients: list[ServiceClient[Any, Any]] = []
        self.rejected_connections = 0

    @property
    def _allows_memory(self) -> bool:
        return self.transport in ("auto", "memory")

    def now_ns(self) -> int:
        """The node's clock, in ns (use for message stamps)."""
        return self.clock.now_ns()

    def resolve(self, name: str) -> str:
        """Absolute name of ``name``: ``/abs`` stays, ``~/x`` is under the node, anything else under the namespace."""
        if not name:
            raise ConfigError("empty topic/service/parameter name")
        if name.startswith("/"):
            return _join(name)
        if name.startswith("~"):
            return _join(self.name, name[1:])
        return _join(self.namespace, name)

    def _start(self, coro: Any, *, name: str) -> asyncio.Task[Any]:
        task = self._tg.create_task(coro, name=name)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    # ---- connections

    async def _connect_to(self, info: dict[str, Any]) -> Transport:
        endpoints: dict[str, str] = info["endpoints"]
        if "memory" in endpoints and info.get("token") == PROCESS_TOKEN:
            return await connect(endpoints["memory"], self.options)
        kind = self.transport
        if kind in ("auto", "memory"):
            kind = "shm" if info.get("host") == HOST_ID and "shm" in endpoints else "tcp"
        if kind not in endpoints:
            raise ConfigError(f"{info.get('node')} offers {sorted(endpoints)}, not {kind}")
        return await connect(endpoints[kind], self.options)

    async def _accept_loop(self, listener: Listener) -> None:
        while True:
            try:
                conn = await listener.accept()
            except TransportClosedError:
                return
            self._start(self._handle_conn(conn), name=f"{self.name} conn {conn.peer}")

    async def _handle_conn(self, conn: Transport) -> None:
        try:
            async with asyncio.timeout(_HELLO_TIMEOUT_S):
                hello = codec.decode_plain(await conn.receive())
            if not isinstance(hello, dict):
                raise CodecError(f"expected a hello map, got {type(hello).__name__}")
            op = hello.get("op")
            if op == "subscribe":
                topic, type_name = hello["topic"], hello["type"]
                pubs = [p for p in self._publishers if p.topic == topic]
                if not pubs:
                    await conn.send(codec.encode_plain({"ok": False, "error": f"{self.name} does not publish {topic}"}))
                    await conn.aclose()
                    return
                pub = pubs[0]
                if pub.msg_type.__name__ != type_name:
                    err = f"{topic} carries {pub.msg_type.__name__}, not {type_name}"
                    await conn.send(codec.encode_plain({"ok": False, "error": err}))
                    await conn.aclose()
                    return
                await conn.send(codec.encode_plain({"ok": True}))
                await pub._serve_sink(conn, QoS.from_wire(hello.get("qos")))
            elif op == "call":
                svc = self._services.get(hello.get("service", ""))
                if svc is None:
                    await conn.aclose()
                    return
                await svc._serve_conn(conn)
            else:
                raise CodecError(f"unknown hello op {op!r}")
        except (CodecError, KeyError, TimeoutError, ConfigError) as exc:
            self.rejected_connections += 1
            logger.warning("%s: rejected a connection from %s: %r", self.name, conn.peer, exc)
            await conn.aclose()
        except (TransportBrokenError, TransportClosedError):
            await conn.aclose()

    def _on_notify(self, msg: dict[str, Any]) -> None:
        if msg.get("op") == "publishers":
            for sub in self._subscriptions:
                if sub.topic == msg["topic"]:
                    sub._update_publishers(msg["publishers"])

    # ---- public API

    async def create_publisher(self, msg_type: type[M], topic: str, *, qos: QoS | None = None) -> Publisher[M]:
        """Advertise ``topic`` carrying ``msg_type``.

        Raises:
            DomainError: the topic already carries another type in this domain.
        """
        topic = self.resolve(topic)
        pub = Publisher(self, msg_type, topic, qos or latest())
        await self._registry.request("advertise", topic=topic, type=msg_type.__name__, node=self.name)
        self._publishers.append(pub)
        _LOCAL_PUBS[(self.domain_id, topic)].append(pub)
        return pub

    async def create_subscription(
        self,
        msg_type: type[M],
        topic: str,
        callback: Callable[[M], Any] | None = None,
        *,
        qos: QoS | None = None,
        zero_copy: bool = False,
    ) -> Subscription[M]:
        """Subscribe to ``topic``.

        Args:
            msg_type: the message class (checked against the topic's type in the domain).
            topic: relative or absolute topic name.
            callback: called (sync or async) for every message, in order, from the node's own task.
            qos: ``latest()`` (default) or ``reliable(depth)``.
            zero_copy: for large arrays over shared memory: decode in place and call ``callback`` at once from
                the receiving task; the message is valid only during the callback (copy what you keep).

        Raises:
            DomainError: the topic carries another type.
        """
        topic = self.resolve(topic)
        if zero_copy and callback is None:
            raise ConfigError("zero_copy=True needs a callback: the message is only valid during it")
        sub = Subscription(self, msg_type, topic, qos or latest(), callback, zero_copy)
        publishers = await self._registry.request("subscribe", topic=topic, type=msg_type.__name__, node=self.name)
        self._subscriptions.append(sub)
        if self._allows_memory:
            _LOCAL_SUBS[(self.domain_id, topic)].append(sub)
        if callback is not None and not zero_copy:
            self._start(sub._dispatch(), name=f"callback {topic}")
        sub._update_publishers(publishers)
        return sub

    def create_timer(
        self, period_s: float, callback: Callable[[], Any], *, start_ns: int | None = None, history: int = 100_000
    ) -> Timer:
        """Call ``callback`` (sync or async) every ``period_s`` of the node's clock, from ``start_ns`` (default:
        one period from now)."""
        timer = Timer(self, period_s, callback, history)
        timer._task = self._start(timer._run(start_ns), name=f"timer {period_s}s")
        self._timers.append(timer)
        return timer

    async def create_service(
        self, req_type: type[Req], resp_type: type[Resp], name: str, handler: Callable[[Req], Any]
    ) -> Service[Req, Resp]:
        """Provide service ``name``.

        Raises:
            NameConflictError: another node provides it.
        """
        name = self.resolve(name)
        svc = Service(self, req_type, resp_type, name, handler)
        await self._registry.request(
            "advertise_service", name=name, node=self.name, req=req_type.__name__, resp=resp_type.__name__
        )
        self._services[name] = svc
        _LOCAL_SERVICES[(self.domain_id, name)] = svc
        return svc

    def create_client(self, req_type: type[Req], resp_type: type[Resp], name: str) -> ServiceClient[Req, Resp]:
        """A client of service ``name`` (closed with the node, or by ``aclose()``)."""
        client = ServiceClient(self, req_type, resp_type, self.resolve(name))
        self._clients.append(client)
        return client

    # ---- parameters

    async def get_parameter(self, name: str, default: Any = ...) -> Any:
        """Value of parameter ``name`` (a namespace prefix returns the nested mapping below it).

        Raises:
            KeyError: not set and no ``default`` given.
        """
        res = await self._registry.request("param_get", name=self.resolve(name))
        if not res["found"]:
            if default is ...:
                raise KeyError(f"parameter {self.resolve(name)!r} is not set")
            return default
        return res["value"]

    async def set_parameter(self, name: str, value: Any) -> None:
        """Set ``name`` (a mapping value sets every key below it)."""
        await self._registry.request("param_set", name=self.resolve(name), value=value)

    async def delete_parameter(self, name: str) -> int:
        """Delete ``name`` and everything below it; returns how many keys went."""
        return int(await self._registry.request("param_delete", name=self.resolve(name)))

    async def list_parameters(self, prefix: str = "/") -> list[str]:
        return list(await self._registry.request("param_list", prefix=self.resolve(prefix)))

    async def load_parameters(self, source: str | Path | dict[str, Any], namespace: str = "") -> int:
        """Set parameters from a YAML file or mapping, under ``namespace`` (default: the node's namespace).

        Returns:
            The number of keys set.

        Raises:
            ConfigError: the file is missing, not YAML, or not a mapping at the top.
        """
        data = load_yaml(source) if isinstance(source, str | Path) else source
        if not isinstance(data, dict):
            raise ConfigError(f"parameters must be a mapping at the top level, got {type(data).__name__}")
        base = self.resolve(namespace) if namespace else (self.namespace or "/")
        n = 0
        for k, v in data.items():
            n += int(await self._registry.request("param_set", name=_join(base, str(k)), value=v))
        return n

    # ---- introspection

    async def list_nodes(self) -> list[str]:
        return list(await self._registry.request("list_nodes"))

    async def list_topics(self) -> list[dict[str, Any]]:
        return list(await self._registry.request("list_topics"))

    async def list_services(self) -> list[dict[str, Any]]:
        return list(await self._registry.request("list_services"))


def _domain_uri(domain: str | Domain | None) -> str:
    if isinstance(domain, Domain):
        return domain.uri
    if domain:
        return domain
    env = os.environ.get("UNIROS_DOMAIN")
    if not env:
        raise ConfigError("no domain given: pass domain=URI (from open_domain().uri) or set UNIROS_DOMAIN")
    return env


@contextlib.asynccontextmanager
async def open_node(
    name: str,
    *,
    domain: str | Domain | None = None,
    namespace: str = "",
    clock: Clock | None = None,
    transport: str = "auto",
    options: TransportOptions | None = None,
    registry_timeout_s: float = 5.0,
) -> AsyncIterator[Node]:
    """Join a domain as node ``name`` for the duration of the block.

    Args:
        name: the node's name (unique in the domain within its namespace).
        domain: a Domain, its URI, or None for ``$UNIROS_DOMAIN``.
        namespace: prefix of the node's relative names (``/rx200_1``).
        clock: the domain's clock (default: the wall clock); timers and stamps follow it.
        transport: ``auto`` (in-process, then shm on one machine, else tcp), or force ``memory``, ``shm``, ``tcp``.
        options: transport options (``auth_key`` must match the domain's and the peers').
        registry_timeout_s: bound on every request to the registry.

    Raises:
        DomainError: the domain is unreachable within ``options.connect_timeout_s``.
        NameConflictError: the node name is taken.
    """
    options = options or TransportOptions()
    uri = _domain_uri(domain)
    node = Node(name, namespace, clock or wall_clock(), transport, options)
    async with unwrap_task_group() as tg:
        node._tg = tg
        try:
            try:
                conn = await connect(uri, options)
            except (TimeoutError, OSError, TransportError) as exc:
                raise DomainError(f"cannot reach the domain at {uri}: {exc}") from exc
            node._registry = _RegistryClient(conn, registry_timeout_s, node._on_notify)
            node._start(node._registry.run(), name=f"{node.name} registry")
            if uri.startswith("memory://"):  # an in-process domain: peers can only be in this process
                node._listeners["memory"] = await listen("memory://", options)
            else:
                node._listeners["tcp"] = await listen(f"tcp://{options.bind_host}:0", options)
            if transport in ("auto", "shm") and "tcp" in node._listeners:
                try:
                    node._listeners["shm"] = await listen("shm://", options)
                except (ImportError, OSError, ConfigError) as exc:  # pragma: no cover - non-Linux
                    logger.info("shared memory unavailable (%s); %s uses tcp only", exc, node.name)
            for lst in node._listeners.values():
                node._start(node._accept_loop(lst), name=f"{node.name} accept {lst.uri}")
            hello = await node._registry.request(
                "hello",
                token=PROCESS_TOKEN,
                host=HOST_ID,
                pid=os.getpid(),
                endpoints={k: lst.uri for k, lst in node._listeners.items()},
            )
            node.domain_id = hello["domain_id"]
            node.domain_uri = uri
            await node._registry.request("register_node", name=node.name)
            yield node
        finally:
            await _close_node(node)


async def _close_node(node: Node) -> None:
    for timer in node._timers:
        timer.cancel()
    for sub in list(node._subscriptions):
        with contextlib.suppress(ValueError):
            _LOCAL_SUBS[(node.domain_id, sub.topic)].remove(sub)
        sub._closed = True
        sub._wake.set()
    for pub in node._publishers:
        pub._closed = True
        with contextlib.suppress(ValueError):
            _LOCAL_PUBS[(node.domain_id, pub.topic)].remove(pub)
    for sname in node._services:
        _LOCAL_SERVICES.pop((node.domain_id, sname), None)
    for client in list(node._clients):
        await client.aclose()
    reader_alive = any(t.get_name() == f"{node.name} registry" and not t.done() for t in node._tasks)
    if node._registry is not None and not node._registry.closed and reader_alive:
        with contextlib.suppress(DomainError, TimeoutError):
            async with asyncio.timeout(1.0):
                await node._registry.request("unregister_node", name=node.name)
    for lst in node._listeners.values():
        await lst.aclose()
    for task in list(node._tasks):
        task.cancel()
    if node._registry is not None:
        await node._registry._conn.aclose()
