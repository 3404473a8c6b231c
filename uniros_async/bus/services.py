"""Services: request/response with timeouts; in-process calls skip the transport."""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import logging
import traceback
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Generic, TypeVar

from uniros_async.bus import codec
from uniros_async.bus._local import (
    _LOCAL_SERVICES,
)
from uniros_async.errors import (
    CodecError,
    DomainError,
    ServiceError,
    TransportBrokenError,
    TransportClosedError,
)
from uniros_async.transports.base import Transport

if TYPE_CHECKING:
    from uniros_async.bus.node import Node

logger = logging.getLogger(__name__)

M = TypeVar("M")
Req = TypeVar("Req")
Resp = TypeVar("Resp")


class Service(Generic[Req, Resp]):
    """Answers ``Req`` with ``Resp`` by calling ``handler`` (sync or async)."""

    def __init__(
        self, node: Node, req_type: type[Req], resp_type: type[Resp], name: str, handler: Callable[[Req], Any]
    ):
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
            raise ServiceError(
                f"service {self.name}: handler returned {type(resp).__name__}, expected {self.resp_type.__name__}"
            )
        return resp

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
            raise CodecError(
                f"service {self.name}: expected request {self.req_type.__name__}, got {type(req).__name__}"
            )
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
