"""Domains: an isolated graph with its own registry of nodes, topics, services and parameters.

A domain is what a separate roscore was in UniROS. ``open_domain()`` serves its registry from the calling
process, on a free port, from Python (no CLI, no daemon), over ``tcp://`` or, encrypted, ``tls://`` (then every
node of the domain reaches its peers on other machines over tls too); nodes join by URI (``UNIROS_DOMAIN``, the
ROS_MASTER_URI of this world). Several domains run side by side without crosstalk: each has its own id, and
in-process delivery is keyed by that id.

The registry only brokers: it tells subscribers where publishers listen and clients where services are. Data
never passes through it. When a node's connection to the registry drops (the node's process exited or died),
everything that node registered is removed and subscribers are told, so a crashed robot leaves no ghosts. A node
whose connection broke while it lives connects again and registers everything it holds (``registry_client``); the
registry knows it by the incarnation id it registered with, so its new connection takes over what the old one,
not yet noticed as dead, still holds. A registry restarted at the same URI (same process or a new one) gets the
graph back that way from its nodes, parameters included.

Registry protocol (msgpack maps over any Transport): requests ``{"op", "id", ...}``, replies ``{"id", "ok",
"result" | "error", "kind"}``, and notifications without an id (``{"op": "publishers", "topic", "publishers"}``).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import uuid
from collections.abc import AsyncIterator
from typing import Any

from uniros_async._log_throttle import LogThrottle
from uniros_async.bus.codec import decode_plain, encode_plain
from uniros_async.bus.tasks import unwrap_task_group
from uniros_async.errors import CodecError, TransportBrokenError, TransportClosedError
from uniros_async.transports.base import Listener, Transport, TransportOptions, listen, options_from_environ

__all__ = ["Domain", "open_domain"]

logger = logging.getLogger(__name__)


@dataclasses.dataclass
class _Participant:
    conn: Transport
    info: dict[str, Any]
    nodes: set[str] = dataclasses.field(default_factory=set)
    send_lock: asyncio.Lock = dataclasses.field(default_factory=asyncio.Lock)


@dataclasses.dataclass
class _Topic:
    type: str
    publishers: dict[str, _Participant] = dataclasses.field(default_factory=dict)  # node -> participant
    subscribers: dict[str, _Participant] = dataclasses.field(default_factory=dict)


class _RequestError(Exception):
    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


class Domain:
    """A running domain registry. Use ``async with open_domain() as domain:``; ``domain.uri`` is what nodes join."""

    def __init__(self, listener: Listener, params: dict[str, Any] | None) -> None:
        self._listener = listener
        self.domain_id = uuid.uuid4().hex
        self._participants: dict[int, _Participant] = {}
        self._nodes: dict[str, _Participant] = {}
        self._incarnations: dict[str, str] = {}  # node -> the id it registered with (a rejoin brings the same)
        self._topics: dict[str, _Topic] = {}
        self._services: dict[str, tuple[_Participant, dict[str, Any]]] = {}
        self.params: dict[str, Any] = dict(params or {})
        self.rejected_requests = 0
        self._log = LogThrottle(logger)  # peers choose how many bad requests they send: one warning a second
        self._pending_notify: set[str] = set()  # topics whose subscribers must hear of publisher changes

    @property
    def uri(self) -> str:
        """The URI nodes join with (``UNIROS_DOMAIN``)."""
        return self._listener.uri

    # ------------------------------------------------------------------------------------------- serving

    async def _serve(self, tg: asyncio.TaskGroup) -> None:
        while True:
            try:
                conn = await self._listener.accept()
            except TransportClosedError:
                return
            tg.create_task(self._serve_participant(conn))

    async def _serve_participant(self, conn: Transport) -> None:
        p = _Participant(conn, {})
        self._participants[id(p)] = p
        try:
            while True:
                frame = await conn.receive()
                try:
                    req = decode_plain(frame)
                    if not isinstance(req, dict) or "op" not in req:
                        raise CodecError(f"expected a request map with 'op', got {type(req).__name__}")
                except CodecError as exc:
                    self.rejected_requests += 1
                    self._log.warning("domain %s: rejected a malformed request from %s: %s", self.uri, conn.peer, exc)
                    continue
                rid = req.get("id")
                try:
                    result = self._handle(p, req)
                    reply = {"id": rid, "ok": True, "result": result}
                except _RequestError as exc:
                    self.rejected_requests += 1
                    reply = {"id": rid, "ok": False, "kind": exc.kind, "error": str(exc)}
                except (KeyError, TypeError, ValueError) as exc:
                    self.rejected_requests += 1
                    reply = {"id": rid, "ok": False, "kind": "bad_request", "error": f"{req.get('op')!r}: {exc!r}"}
                await self._send(p, reply)
                await self._flush_notifications()
        except (TransportBrokenError, TransportClosedError):
            pass
        finally:
            self._participants.pop(id(p), None)
            self._drop_participant(p)
            await conn.aclose()
            with contextlib.suppress(TransportBrokenError, TransportClosedError):
                await self._flush_notifications()

    async def _send(self, p: _Participant, msg: dict[str, Any]) -> None:
        async with p.send_lock:
            with contextlib.suppress(TransportBrokenError, TransportClosedError):
                await p.conn.send(encode_plain(msg))

    # ------------------------------------------------------------------------------------------- requests

    def _handle(self, p: _Participant, req: dict[str, Any]) -> Any:
        op = req["op"]
        handler = getattr(self, f"_op_{op}", None)
        if handler is None:
            raise _RequestError("bad_request", f"unknown registry operation {op!r}")
        return handler(p, req)

    def _op_hello(self, p: _Participant, req: dict[str, Any]) -> Any:
        p.info = {"token": req["token"], "host": req["host"], "pid": req["pid"], "endpoints": req["endpoints"]}
        return {"domain_id": self.domain_id}

    def _op_register_node(self, p: _Participant, req: dict[str, Any]) -> Any:
        name, incarnation = req["name"], req.get("incarnation")
        old = self._nodes.get(name)
        if old is not None and old is not p:
            if incarnation is None or self._incarnations.get(name) != incarnation:
                raise _RequestError("name_conflict", f"a node named {name!r} already exists in this domain")
            self._take_over(old, p, name)  # the same node rejoining over a new connection
        self._nodes[name] = p
        if isinstance(incarnation, str):
            self._incarnations[name] = incarnation
        p.nodes.add(name)
        return None

    def _take_over(self, old: _Participant, p: _Participant, node: str) -> None:
        """Move what ``node`` registered over its old connection ``old`` to its new one ``p``."""
        old.nodes.discard(node)
        for t in self._topics.values():
            if t.publishers.get(node) is old:
                t.publishers[node] = p
            if t.subscribers.get(node) is old:
                t.subscribers[node] = p
        for sname, (sp, info) in list(self._services.items()):
            if sp is old and info["node"] == node:
                self._services[sname] = (p, {**info, **p.info})

    def _op_unregister_node(self, p: _Participant, req: dict[str, Any]) -> Any:
        self._drop_node(p, req["name"])
        return None

    def _topic(self, name: str, type_name: str) -> _Topic:
        t = self._topics.get(name)
        if t is None:
            t = self._topics[name] = _Topic(type_name)
        elif t.type != type_name:
            if not t.publishers and not t.subscribers:
                t.type = type_name
            else:
                raise _RequestError("type_mismatch", f"topic {name!r} carries {t.type}, not {type_name}")
        return t

    def _pub_list(self, t: _Topic) -> list[dict[str, Any]]:
        return [{"node": n, **p.info} for n, p in t.publishers.items()]

    def _op_advertise(self, p: _Participant, req: dict[str, Any]) -> Any:
        t = self._topic(req["topic"], req["type"])
        t.publishers[req["node"]] = p
        self._notify(req["topic"])
        return None

    def _op_unadvertise(self, p: _Participant, req: dict[str, Any]) -> Any:
        t = self._topics.get(req["topic"])
        if t is not None and t.publishers.pop(req["node"], None) is not None:
            self._notify(req["topic"])
        return None

    def _op_subscribe(self, p: _Participant, req: dict[str, Any]) -> Any:
        t = self._topic(req["topic"], req["type"])
        t.subscribers[req["node"]] = p
        return self._pub_list(t)

    def _op_unsubscribe(self, p: _Participant, req: dict[str, Any]) -> Any:
        t = self._topics.get(req["topic"])
        if t is not None:
            t.subscribers.pop(req["node"], None)
        return None

    def _op_advertise_service(self, p: _Participant, req: dict[str, Any]) -> Any:
        name = req["name"]
        if name in self._services:
            owner = self._services[name][1]["node"]
            if owner != req["node"] or self._nodes.get(owner) is not p:  # else: its node advertises it again
                raise _RequestError("name_conflict", f"service {name!r} is already provided by {owner}")
        self._services[name] = (
            p,
            {"name": name, "node": req["node"], "req": req["req"], "resp": req["resp"], **p.info},
        )
        return None

    def _op_unadvertise_service(self, p: _Participant, req: dict[str, Any]) -> Any:
        entry = self._services.get(req["name"])
        if entry is not None and entry[0] is p:
            del self._services[req["name"]]
        return None

    def _op_lookup_service(self, p: _Participant, req: dict[str, Any]) -> Any:
        entry = self._services.get(req["name"])
        if entry is None:
            raise _RequestError(
                "not_found", f"no service {req['name']!r} in this domain; known: {sorted(self._services)}"
            )
        return entry[1]

    def _op_list_nodes(self, p: _Participant, req: dict[str, Any]) -> Any:
        return sorted(self._nodes)

    def _op_list_topics(self, p: _Participant, req: dict[str, Any]) -> Any:
        return [
            {"topic": n, "type": t.type, "publishers": sorted(t.publishers), "subscribers": sorted(t.subscribers)}
            for n, t in sorted(self._topics.items())
            if t.publishers or t.subscribers
        ]

    def _op_list_services(self, p: _Participant, req: dict[str, Any]) -> Any:
        return [
            {"service": n, "node": e[1]["node"], "req": e[1]["req"], "resp": e[1]["resp"]}
            for n, e in sorted(self._services.items())
        ]

    def _op_param_get(self, p: _Participant, req: dict[str, Any]) -> Any:
        name = req["name"]
        if name in self.params:
            return {"found": True, "value": self.params[name]}
        prefix = name.rstrip("/") + "/"
        sub = {k[len(prefix) :]: v for k, v in self.params.items() if k.startswith(prefix)}
        if sub:
            return {"found": True, "value": _unflatten(sub)}
        return {"found": False, "value": None}

    def _op_param_set(self, p: _Participant, req: dict[str, Any]) -> Any:
        name, value = req["name"], req["value"]
        if not name.startswith("/"):
            raise _RequestError("bad_request", f"parameter names given to the registry are absolute, got {name!r}")
        items = _flatten(name, value)
        for k in [k for k in self.params if k == name or k.startswith(name.rstrip("/") + "/")]:
            del self.params[k]
        self.params.update(items)
        return len(items)

    def _op_param_delete(self, p: _Participant, req: dict[str, Any]) -> Any:
        name = req["name"]
        keys = [k for k in self.params if k == name or k.startswith(name.rstrip("/") + "/")]
        for k in keys:
            del self.params[k]
        return len(keys)

    def _op_param_list(self, p: _Participant, req: dict[str, Any]) -> Any:
        prefix = req.get("prefix", "/")
        return sorted(k for k in self.params if k.startswith(prefix))

    # ------------------------------------------------------------------------------------------- cleanup

    def _drop_node(self, p: _Participant, node: str) -> None:
        if self._nodes.get(node) is p:
            del self._nodes[node]
            self._incarnations.pop(node, None)
        p.nodes.discard(node)
        for name, t in self._topics.items():
            if t.publishers.get(node) is p:
                del t.publishers[node]
                self._notify(name)
            if t.subscribers.get(node) is p:
                del t.subscribers[node]
        for sname in [s for s, (sp, info) in self._services.items() if sp is p and info["node"] == node]:
            del self._services[sname]

    def _drop_participant(self, p: _Participant) -> None:
        for node in list(p.nodes):
            self._drop_node(p, node)

    def _notify(self, topic: str) -> None:
        self._pending_notify.add(topic)

    async def _flush_notifications(self) -> None:
        while self._pending_notify:
            topic = self._pending_notify.pop()
            t = self._topics.get(topic)
            if t is None:
                continue
            msg = {"op": "publishers", "topic": topic, "publishers": self._pub_list(t)}
            for p in {id(p): p for p in t.subscribers.values()}.values():
                await self._send(p, msg)


def _flatten(name: str, value: Any) -> dict[str, Any]:
    if isinstance(value, dict) and value:
        out: dict[str, Any] = {}
        for k, v in value.items():
            out.update(_flatten(f"{name.rstrip('/')}/{k}", v))
        return out
    return {name: value}


def _unflatten(flat: dict[str, Any]) -> dict[str, Any]:
    root: dict[str, Any] = {}
    for key, value in flat.items():
        parts = key.split("/")
        node = root
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return root


@contextlib.asynccontextmanager
async def open_domain(
    uri: str = "tcp://127.0.0.1:0",
    *,
    params: dict[str, Any] | None = None,
    options: TransportOptions | None = None,
) -> AsyncIterator[Domain]:
    """Serve a new domain registry from this process until the block exits.

    Args:
        uri: where to listen: ``tcp://127.0.0.1:0`` (a free port, reachable from other processes),
            ``tls://HOST:PORT`` (the same over mutual TLS: the registry and every node's peer connections across
            machines are encrypted, and each process needs a certificate signed by the domain's CA), or
            ``memory://`` (this process only).
        params: initial parameters, nested mappings flattened to absolute ``/a/b`` names.
        options: transport options (``auth_key`` makes every node prove the shared key; ``tls_cert_file``,
            ``tls_key_file``, ``tls_ca_file`` for ``tls://``); None: defaults, with ``auth_key`` from
            ``$UNIROS_AUTH_KEY`` when set and the TLS files from ``$UNIROS_TLS_CERT``, ``$UNIROS_TLS_KEY`` and
            ``$UNIROS_TLS_CA``.

    Yields:
        The running Domain; ``domain.uri`` is what nodes join.

    Raises:
        ConfigError: a malformed URI, a non-loopback ``tcp://`` host without ``auth_key`` (or ``insecure``), or a
            ``tls://`` domain without its certificate, key or CA (the message names the options and variables).
        OSError: the address cannot be bound.
    """
    listener = await listen(uri, options or options_from_environ())
    flat: dict[str, Any] = {}
    for k, v in (params or {}).items():
        flat.update(_flatten(k if k.startswith("/") else "/" + k, v))
    domain = Domain(listener, flat)
    try:
        async with unwrap_task_group() as tg:
            server = tg.create_task(domain._serve(tg))
            try:
                yield domain
            finally:
                server.cancel()
                await listener.aclose()
                for p in list(domain._participants.values()):
                    await p.conn.aclose()
    finally:
        await listener.aclose()
