"""A node's connection to its domain registry: requests with ids, pushed notifications, and rejoining.

When the connection breaks (the registry's process died or was restarted, the link was cut past the keepalive, the
registry's port blocked), the client connects again to the same URI, starting an attempt after each capped backoff
delay (``REJOIN_FIRST_S`` doubling to ``REJOIN_MAX_S``; attempts overlap, each bounded by ``REJOIN_ATTEMPT_S``) for as
long as the node lives, and then calls ``on_rejoin``: the node registers everything it holds again
(``Node._register_all``). Requests made while the connection is down fail at once with ``DomainError``; data between
nodes does not pass through the registry and keeps flowing where its own connections hold.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import logging
from collections.abc import Awaitable, Callable
from typing import Any

from uniros_async.backoff import Backoff
from uniros_async.bus import codec
from uniros_async.errors import (
    CodecError,
    DomainError,
    NameConflictError,
    TransportBrokenError,
    TransportClosedError,
    TransportError,
)
from uniros_async.transports.base import Transport, TransportOptions, connect

logger = logging.getLogger(__name__)

REJOIN_FIRST_S = 0.05
"""First wait between attempts to reach a lost registry again."""
REJOIN_MAX_S = 0.25
"""Longest wait between the starts of two attempts (a registry that answers again is rejoined within about this,
plus one connection's round trips)."""
REJOIN_ATTEMPT_S = 1.0
"""Bound on one attempt (connect and handshake), which may take this long over a starved link; attempts overlap, so
a SYN lost in a cut link does not hold the next one back. The node's first connection uses the full
``connect_timeout_s``."""


class _RegistryClient:
    """This node's connection to its domain registry: requests with ids, pushed notifications, and rejoining.

    Args:
        conn: the connection, already made.
        timeout_s: bound on every request.
        on_notify: called with every notification (a message without an id).
        uri: the registry's URI, to connect to again when the connection breaks; None: no rejoining.
        options: transport options for those connections.
        on_rejoin: awaited after each new connection, to register again; a ``DomainError`` from it drops the
            connection and the client tries again.
    """

    def __init__(
        self,
        conn: Transport,
        timeout_s: float,
        on_notify: Callable[[dict[str, Any]], None],
        *,
        uri: str | None = None,
        options: TransportOptions | None = None,
        on_rejoin: Callable[[], Awaitable[None]] | None = None,
    ) -> None:
        self._conn = conn
        self._timeout_s = timeout_s
        self._ids = itertools.count(1)
        self._waiting: dict[int, asyncio.Future[Any]] = {}
        self._on_notify = on_notify
        self._lock = asyncio.Lock()
        self._uri = uri
        self._options = options
        self._on_rejoin = on_rejoin
        self.closed = False
        """The connection is down (for good once the node closes, else until rejoined)."""
        self.closing = False
        """The node is leaving: a broken connection is not made again."""
        self.rejoins = 0
        """How many times the registry was reached again after the connection broke."""
        self.rejoined = asyncio.Event()
        """Set after each rejoin completes (the node registered everything again); cleared when the connection
        breaks."""

    async def run(self) -> None:
        """Read replies and notifications; when the connection breaks, connect again and rejoin (until closed)."""
        while True:
            async with asyncio.TaskGroup() as tg:
                if self.rejoins and self._on_rejoin is not None:
                    tg.create_task(self._rejoin())
                await self._read()
            if self.closing or self._uri is None:
                return
            self._conn = await self._reconnect(self._uri)
            self.closed = False
            self.rejoins += 1

    async def _read(self) -> None:
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
            self.rejoined.clear()
            for fut in self._waiting.values():
                if not fut.done():
                    fut.set_exception(DomainError(f"lost the connection to the domain registry: {exc}"))
            self._waiting.clear()
            await self._conn.aclose()
            if not self.closing:
                again = "; connecting again" if self._uri is not None else ""
                logger.error("lost the connection to the domain registry at %s: %s%s", self._conn.peer, exc, again)

    async def _reconnect(self, uri: str) -> Transport:
        """Connect to ``uri`` again until it answers (cancelled when the node closes).

        A new attempt starts after each backoff delay (``REJOIN_FIRST_S`` doubling to ``REJOIN_MAX_S``) whether or
        not the earlier ones have ended, each bounded by ``REJOIN_ATTEMPT_S``; the first to connect wins and the
        others are cancelled (or closed, when they connected too). A link that comes back is so tried within
        ``REJOIN_MAX_S``, not after an attempt whose SYN the cut link dropped has run out its bound."""
        options = self._options or TransportOptions()
        attempt = dataclasses.replace(options, connect_timeout_s=min(options.connect_timeout_s, REJOIN_ATTEMPT_S))
        backoff = Backoff(first_s=REJOIN_FIRST_S, max_s=REJOIN_MAX_S)
        won: asyncio.Future[Transport] = asyncio.get_running_loop().create_future()

        async def try_once() -> None:
            try:
                conn = await connect(uri, attempt)
            except (TimeoutError, OSError, TransportError) as exc:
                logger.debug("domain registry at %s not back yet: %s", uri, exc)
                return
            if won.done():
                await conn.aclose()
            else:
                won.set_result(conn)

        try:
            async with asyncio.TaskGroup() as tg:
                tries: list[asyncio.Task[None]] = []
                while not won.done():
                    tries = [t for t in tries if not t.done()]
                    tries.append(tg.create_task(try_once()))
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(backoff.next_s()):
                            await asyncio.shield(won)
                for t in tries:
                    t.cancel()
        except BaseException:  # the node closing: a connection that won meanwhile is not left open
            if won.done():
                await won.result().aclose()
            raise
        return won.result()

    async def _rejoin(self) -> None:
        assert self._on_rejoin is not None
        try:
            await self._on_rejoin()
        except (DomainError, NameConflictError) as exc:
            # the registry refused or the connection broke again: drop it, and the next connection tries again
            logger.warning("rejoining the domain at %s failed (%s); trying again", self._uri, exc)
            await asyncio.sleep(REJOIN_MAX_S)
            await self._conn.aclose()
            return
        self.rejoined.set()
        logger.warning("rejoined the domain at %s", self._uri)

    async def request(self, op: str, **kw: Any) -> Any:
        if self.closed:
            raise DomainError("the connection to the domain registry is down (the node is connecting again)")
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
