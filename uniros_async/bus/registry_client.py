"""A node's connection to its domain registry: requests with ids, and pushed notifications."""

from __future__ import annotations

import asyncio
import itertools
import logging
from collections.abc import Callable
from typing import Any, TypeVar

from uniros_async.bus import codec
from uniros_async.errors import (
    CodecError,
    DomainError,
    NameConflictError,
    TransportBrokenError,
    TransportClosedError,
    TransportError,
)
from uniros_async.transports.base import Transport

logger = logging.getLogger(__name__)

M = TypeVar("M")
Req = TypeVar("Req")
Resp = TypeVar("Resp")


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
