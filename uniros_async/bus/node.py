"""Nodes, publishers, subscriptions, timers, services and parameters.

A node joins a domain (``open_node("name", domain=uri)``); everything it creates is named relative to its
namespace (``"joint_states"`` in namespace ``/rx200_1`` is ``/rx200_1/joint_states``; ``"/clock"`` is absolute;
``"~/status"`` is under the node's own name). The transport of a topic connection is chosen per connection:

- same process (and same domain): no transport at all, the subscriber gets the message object itself;
- same machine: ``shm://`` (shared-memory rings), unless the node asked for ``transport="tcp"`` (or ``"tls"``);
- otherwise the domain's network scheme: ``tcp://``, or ``tls://`` for a domain served on ``tls://`` (every node of
  such a domain listens for its peers on ``tls://`` and offers no clear tcp endpoint, so nothing of it crosses the
  network unencrypted; shm stays: it never leaves the machine).

Publishing never blocks: ``publish`` hands the message to in-process subscribers and the encoded frame (encoded
once, however many remote subscribers) to one bounded queue per remote subscriber, which a sender task drains.
What the queues keep when full is the topic's QoS (``latest`` or ``reliable(depth)``, see qos.py).

Every task a node starts belongs to the node's TaskGroup; leaving ``async with open_node(...)`` cancels them and
closes every connection. A timer or subscription callback that raises ends the node with that error (a bug
should not be hidden); a malformed frame from a peer is counted in ``rejected`` and logged, never fatal.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import uuid
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any, TypeVar

from uniros_async._log_throttle import LogThrottle
from uniros_async.bus import codec
from uniros_async.bus._local import (
    _HELLO_TIMEOUT_S,
    _LOCAL_PUBS,
    _LOCAL_SERVICES,
    _LOCAL_SUBS,
    HOST_ID,
    NETWORK_SCHEMES,
    PROCESS_TOKEN,
    TRANSPORT_CHOICES,
)
from uniros_async.bus.domain import Domain, _flatten
from uniros_async.bus.pubsub import Publisher, Subscription
from uniros_async.bus.qos import QoS, latest
from uniros_async.bus.registry_client import _RegistryClient
from uniros_async.bus.services import Service, ServiceClient
from uniros_async.bus.tasks import unwrap_task_group
from uniros_async.bus.timer import Timer
from uniros_async.clock import Clock, wall_clock
from uniros_async.errors import (
    CodecError,
    ConfigError,
    DomainError,
    NameConflictError,
    TransportBrokenError,
    TransportClosedError,
    TransportError,
)
from uniros_async.transports.base import Listener, Transport, TransportOptions, connect, listen, options_from_environ

__all__ = ["Node", "Publisher", "Service", "ServiceClient", "Subscription", "Timer", "open_node"]

logger = logging.getLogger(__name__)

M = TypeVar("M")
Req = TypeVar("Req")
Resp = TypeVar("Resp")


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
        self.network = "tcp"  # the scheme peers on other machines are reached by: the domain's (open_node sets it)
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
        self._log = LogThrottle(logger)  # peers choose how many bad connections they make: one warning a second
        self._incarnation = uuid.uuid4().hex  # tells the registry that a rejoin is this node, not another of its name
        self._params: dict[str, Any] = {}  # the parameters this node set (flat), set again in a restarted registry

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
            kind = "shm" if info.get("host") == HOST_ID and "shm" in endpoints else self.network
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
            self._log.warning("%s: rejected a connection from %s: %r", self.name, conn.peer, exc)
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
        self._publishers.append(pub)  # listed first: a rejoin meanwhile advertises it too
        try:
            await self._registry.request("advertise", topic=topic, type=msg_type.__name__, node=self.name)
        except BaseException:
            self._publishers.remove(pub)
            raise
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
        self._subscriptions.append(sub)  # listed first: a rejoin meanwhile subscribes it too
        try:
            publishers = await self._registry.request("subscribe", topic=topic, type=msg_type.__name__, node=self.name)
        except BaseException:
            self._subscriptions.remove(sub)
            raise
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
        if name in self._services:
            raise NameConflictError(f"service {name!r} is already provided by {self.name}")
        self._services[name] = svc  # listed first: a rejoin meanwhile advertises it too
        try:
            await self._registry.request(
                "advertise_service", name=name, node=self.name, req=req_type.__name__, resp=resp_type.__name__
            )
        except BaseException:
            del self._services[name]
            raise
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
        await self._set_param(self.resolve(name), value)

    async def _set_param(self, name: str, value: Any) -> int:
        n = int(await self._registry.request("param_set", name=name, value=value))
        self._forget_params(name)
        self._params.update(_flatten(name, value))
        return n

    def _forget_params(self, name: str) -> None:
        prefix = name.rstrip("/") + "/"
        for k in [k for k in self._params if k == name or k.startswith(prefix)]:
            del self._params[k]

    async def delete_parameter(self, name: str) -> int:
        """Delete ``name`` and everything below it; returns how many keys went."""
        n = int(await self._registry.request("param_delete", name=self.resolve(name)))
        self._forget_params(self.resolve(name))
        return n

    async def list_parameters(self, prefix: str = "/") -> list[str]:
        return list(await self._registry.request("param_list", prefix=self.resolve(prefix)))

    async def load_parameters(self, source: str | Path | dict[str, Any], namespace: str = "") -> int:
        """Set parameters from a YAML file or mapping, under ``namespace`` (default: the node's namespace).

        Returns:
            The number of keys set.

        Raises:
            ConfigError: the file is missing, not YAML, or not a mapping at the top.
        """
        if isinstance(source, str | Path):
            from uniros_async.yamlio import load_yaml  # PyYAML only where a file is read (not in every env worker)

            data = load_yaml(source)
        else:
            data = source
        if not isinstance(data, dict):
            raise ConfigError(f"parameters must be a mapping at the top level, got {type(data).__name__}")
        base = self.resolve(namespace) if namespace else (self.namespace or "/")
        n = 0
        for k, v in data.items():
            n += await self._set_param(_join(base, str(k)), v)
        return n

    # ---- rejoining

    async def _hello(self) -> dict[str, Any]:
        return dict(
            await self._registry.request(
                "hello",
                token=PROCESS_TOKEN,
                host=HOST_ID,
                pid=os.getpid(),
                endpoints={k: lst.uri for k, lst in self._listeners.items()},
            )
        )

    async def _register_all(self) -> None:
        """Register with a registry reached again everything this node holds: the node, its publishers, services
        and subscriptions (whose readers reconnect at once to the publishers named), and, in a registry that was
        restarted (a new domain id), the parameters this node set."""
        reg = self._registry
        hello = await self._hello()
        restarted = hello["domain_id"] != self.domain_id
        if restarted:
            self._rekey(hello["domain_id"])
        await reg.request("register_node", name=self.name, incarnation=self._incarnation)
        for pub in list(self._publishers):
            await reg.request("advertise", topic=pub.topic, type=pub.msg_type.__name__, node=self.name)
        for name, svc in list(self._services.items()):
            await reg.request(
                "advertise_service", name=name, node=self.name, req=svc.req_type.__name__, resp=svc.resp_type.__name__
            )
        for sub in list(self._subscriptions):
            pubs = await reg.request("subscribe", topic=sub.topic, type=sub.msg_type.__name__, node=self.name)
            sub._update_publishers(pubs, restart=True)
        if restarted:
            for name, value in list(self._params.items()):
                await reg.request("param_set", name=name, value=value)

    def _rekey(self, domain_id: str) -> None:
        """Move this node's entries in the in-process delivery tables to a restarted registry's domain id (every
        node of this process in that domain moves as it rejoins; a node joining afterwards gets the new id)."""
        old, self.domain_id = self.domain_id, domain_id
        for pub in self._publishers:
            with contextlib.suppress(ValueError):
                _LOCAL_PUBS[(old, pub.topic)].remove(pub)
            _LOCAL_PUBS[(domain_id, pub.topic)].append(pub)
            pub._local = _LOCAL_SUBS[(domain_id, pub.topic)]
        for sub in self._subscriptions:
            if sub in _LOCAL_SUBS.get((old, sub.topic), ()):
                _LOCAL_SUBS[(old, sub.topic)].remove(sub)
                _LOCAL_SUBS[(domain_id, sub.topic)].append(sub)
        for name, svc in self._services.items():
            if _LOCAL_SERVICES.get((old, name)) is svc:
                del _LOCAL_SERVICES[(old, name)]
            _LOCAL_SERVICES[(domain_id, name)] = svc

    # ---- introspection

    async def list_nodes(self) -> list[str]:
        return list(await self._registry.request("list_nodes"))

    async def list_topics(self) -> list[dict[str, Any]]:
        return list(await self._registry.request("list_topics"))

    async def list_services(self) -> list[dict[str, Any]]:
        return list(await self._registry.request("list_services"))


def _network_scheme(uri: str, transport: str) -> str | None:
    """The scheme a node of the domain at ``uri`` listens on for peers in other processes: ``tls`` in a ``tls://``
    domain, else ``tcp``; None for a ``memory://`` domain (its peers are all in this process).

    Raises:
        ConfigError: ``transport`` forces a network scheme other than the domain's (``tcp`` in a tls domain would
            carry the node's topics in clear; ``tls`` in a tcp domain finds no peer listening on tls).
    """
    scheme = uri.partition("://")[0]
    if scheme == "memory":
        return None
    network = "tls" if scheme == "tls" else "tcp"
    if transport in NETWORK_SCHEMES and transport != network:
        if network == "tls":
            raise ConfigError(
                f"transport='tcp' would carry this node's topics and services in clear, but the domain {uri} is "
                "served on tls://, whose nodes reach each other over tls: use transport='tls' (network only) or "
                "'auto' (shm to peers on this machine, tls to the others)"
            )
        raise ConfigError(
            f"transport='tls' needs a domain served on tls://HOST:PORT; the nodes of {uri} listen on {network}:// "
            "(open the domain with open_domain('tls://HOST:PORT'), or use transport='tcp')"
        )
    return network


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
        transport: ``auto`` (in-process, then shm on one machine, else the domain's scheme: tcp, or tls in a
            ``tls://`` domain), or force ``memory``, ``shm``, ``tcp`` (a tcp domain) or ``tls`` (a tls domain): the
            last two use the network even to peers on this machine.
        options: transport options (``auth_key`` must match the domain's and the peers'; in a ``tls://`` domain the
            node's certificate, key and CA, ``tls_*`` or ``$UNIROS_TLS_CERT``/``KEY``/``CA``); None: defaults, with
            ``auth_key`` from ``$UNIROS_AUTH_KEY`` when set and the TLS files from the environment.
        registry_timeout_s: bound on every request to the registry.

    Raises:
        ConfigError: bad name or transport; a ``tls://`` domain without this node's TLS files.
        DomainError: the domain is unreachable within ``options.connect_timeout_s``, or (``tls://``) refused this
            node's certificate.
        AuthenticationError: the domain failed to prove the shared key, or (``tls://``) its certificate is not
            signed by this node's CA or does not name the host dialled.
        NameConflictError: the node name is taken.
    """
    options = options or options_from_environ()
    uri = _domain_uri(domain)
    node = Node(name, namespace, clock or wall_clock(), transport, options)
    network = _network_scheme(uri, transport)
    node.network = network or "tcp"
    async with unwrap_task_group() as tg:
        node._tg = tg
        try:
            try:
                conn = await connect(uri, options)
            except TransportBrokenError as exc:
                hint = ""
                if network == "tls":  # a tls listener hangs up on a client certificate it cannot verify
                    from uniros_async.transports.tls import CERT_ENV

                    hint = (
                        "; a tls domain hangs up on a node whose certificate is not signed by the domain's CA: check "
                        f"this node's certificate (tls_cert_file or ${CERT_ENV}) against the CA the domain trusts"
                    )
                raise DomainError(f"cannot reach the domain at {uri}: {exc}{hint}") from exc
            except (TimeoutError, OSError, TransportError) as exc:
                raise DomainError(f"cannot reach the domain at {uri}: {exc}") from exc
            node._registry = _RegistryClient(
                conn, registry_timeout_s, node._on_notify, uri=uri, options=options, on_rejoin=node._register_all
            )
            node._start(node._registry.run(), name=f"{node.name} registry")
            if network is None:  # an in-process domain: peers can only be in this process
                node._listeners["memory"] = await listen("memory://", options)
            else:
                node._listeners[network] = await listen(f"{network}://{options.bind_host}:0", options)
            if transport in ("auto", "shm") and network is not None:
                try:
                    node._listeners["shm"] = await listen("shm://", options)
                except (ImportError, OSError, ConfigError) as exc:  # pragma: no cover - non-Linux
                    logger.info("shared memory unavailable (%s); %s uses tcp only", exc, node.name)
            for lst in node._listeners.values():
                node._start(node._accept_loop(lst), name=f"{node.name} accept {lst.uri}")
            hello = await node._hello()
            node.domain_id = hello["domain_id"]
            node.domain_uri = uri
            await node._registry.request("register_node", name=node.name, incarnation=node._incarnation)
            yield node
        finally:
            await _close_node(node)


async def _close_node(node: Node) -> None:
    if node._registry is not None:
        node._registry.closing = True
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
