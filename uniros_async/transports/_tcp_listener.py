"""The server side of ``tcp://`` (and ``tls://``): the listener, its accept queue, its caps and its handshakes.

``open_listener`` binds and hands each accepted connection a ``TcpTransport`` (or a refusal, at
``max_connections``). The transport drives the handshake on its own bytes (``_tcp_handshake``) and reports to its
listener: ``_handshake_started`` admits it among at most ``max_handshakes`` unfinished ones (evicting the oldest
that waited 1 s), ``_handshake_succeeded`` queues it for ``accept``, ``_handshake_rejected`` counts a refusal.
Refusals are counted in ``rejected`` and logged at most once a second, under the tcp transport's logger.
``uniros_async.transports.tcp`` re-exports ``TcpListener`` and ``open_listener``.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import ssl
from collections.abc import Callable
from typing import Any, Generic, Protocol, TypeVar, cast
from urllib.parse import urlsplit

from uniros_async._log_throttle import LogThrottle
from uniros_async.errors import ConfigError, TransportBrokenError, TransportClosedError
from uniros_async.transports._tcp_receive import TcpReceiving
from uniros_async.transports.base import Listener, TransportOptions, split_uri
from uniros_async.transports.exposure import check_exposure

_E = TypeVar("_E", bound=TcpReceiving)
_E_co = TypeVar("_E_co", bound=TcpReceiving, covariant=True)


class AcceptedEnd(Protocol[_E_co]):
    """The class of the ends a listener hands out (``tcp.TcpTransport``, ``tls.TlsTransport``), passed to
    ``open_listener`` so that this module does not import the transport that imports it."""

    @property
    def scheme(self) -> str: ...

    def __call__(self, options: TransportOptions, *, listener: TcpListener[Any]) -> _E_co: ...


__all__ = ["AcceptedEnd", "TcpListener", "format_uri", "open_listener", "parse_host_port"]

logger = logging.getLogger("uniros_async.transports.tcp")  # one name for the whole transport, as users filter it

_EVICT_AFTER_S = 1.0  # beyond max_handshakes, an unfinished handshake this old gives way to a newcomer


class TcpListener(Listener, Generic[_E]):
    """Accepts TCP connections; each peer that passes the handshake is handed out by ``accept``.

    Caps (``TransportOptions``): at most ``max_connections`` open at once (a connection beyond it is closed as soon
    as it is accepted, before any byte is read or any buffer allocated), at most ``max_handshakes`` unfinished (a new
    connection beyond it evicts the oldest unfinished one if that waited 1 s, else is refused and retries), and each
    handshake must finish within ``handshake_timeout_s``. Every refusal is counted in ``rejected`` and logged at
    most once a second.
    """

    def __init__(self, options: TransportOptions) -> None:
        self._options = options
        self._server: asyncio.Server | None = None
        self._uri = ""
        self._address: tuple[str, int] = ("", 0)
        self._ready: collections.deque[_E] = collections.deque()
        self._accept_waiter: asyncio.Future[None] | None = None
        self._handshaking: dict[_E, None] = {}  # insertion order: the oldest is evicted first
        self._open = 0  # connections made and not yet lost, accepted ones included
        self._rejected = 0
        self._closed = False
        self._log = LogThrottle(logger)

    @property
    def uri(self) -> str:
        return self._uri

    @property
    def address(self) -> tuple[str, int]:
        """The (host, port) actually bound."""
        return self._address

    @property
    def rejected(self) -> int:
        return self._rejected

    @property
    def open_connections(self) -> int:
        """Connections open now (handshaking, waiting for ``accept``, and accepted)."""
        return self._open

    @property
    def handshaking(self) -> int:
        """Connections whose handshake is unfinished."""
        return len(self._handshaking)

    async def accept(self) -> _E:
        """Wait for the next peer that completed the handshake. Cancelling loses no peer.

        Raises:
            TransportClosedError: the listener was closed.
        """
        while not self._ready:
            if self._closed:
                raise TransportClosedError(f"listener {self._uri} is closed")
            if self._accept_waiter is not None:
                raise RuntimeError(f"accept() on {self._uri} while another accept() is waiting")
            fut = self._accept_waiter = asyncio.get_running_loop().create_future()
            try:
                await fut
            finally:
                self._accept_waiter = None
        if self._closed:
            raise TransportClosedError(f"listener {self._uri} is closed")
        return self._ready.popleft()

    async def aclose(self) -> None:
        """Stop listening and free the port; idempotent. Accepted transports stay open; connections still in the
        handshake or not yet accepted are closed."""
        if self._closed:
            return
        self._closed = True
        if self._server is not None:
            self._server.close()  # closes the listening sockets now (wait_closed would wait for accepted ones)
        pending = [*self._handshaking, *self._ready]
        self._handshaking.clear()
        self._ready.clear()
        if self._accept_waiter is not None and not self._accept_waiter.done():
            self._accept_waiter.set_result(None)
        for t in pending:
            await t.aclose()

    def _protocol(self, make: Callable[[], _E]) -> asyncio.BaseProtocol:
        """The protocol for a connection just accepted: a transport, or a refusal once ``max_connections`` are
        open."""
        if self._open >= self._options.max_connections:
            return _Refusal(self)
        self._open += 1
        return make()

    def _handshake_started(self, t: _E) -> bool:
        """Admit ``t`` among the unfinished handshakes; False: refuse it (the caller drops it before its HELLO).

        Beyond ``max_handshakes`` the oldest unfinished one is evicted if it has waited at least
        ``_EVICT_AFTER_S`` (a stranger holding connections open), else the newcomer is refused (a burst of peers,
        whose handshakes are about to finish: they retry)."""
        handshaking = self._handshaking
        limit = self._options.max_handshakes
        if len(handshaking) >= limit:
            oldest = next(iter(handshaking))
            waited_s = asyncio.get_running_loop().time() - oldest._hs_started_s
            if waited_s < min(_EVICT_AFTER_S, self._options.handshake_timeout_s / 2):
                self._count_rejection(t.peer, f"over max_handshakes={limit}")
                return False
            oldest._handshake_failed(
                TransportBrokenError(
                    f"{oldest.peer} evicted after {waited_s:.1f} s: more than max_handshakes={limit} unfinished"
                )
            )
        handshaking[t] = None
        return True

    def _handshake_succeeded(self, t: _E) -> None:
        self._handshaking.pop(t, None)
        if self._closed:
            t._tr.close()  # type: ignore[union-attr]
            return
        self._ready.append(t)
        if self._accept_waiter is not None and not self._accept_waiter.done():
            self._accept_waiter.set_result(None)

    def _handshake_rejected(self, t: _E, reason: str) -> None:
        self._handshaking.pop(t, None)
        if not self._closed:
            self._count_rejection(t.peer, reason)

    def _count_rejection(self, peer: str, reason: str) -> None:
        self._rejected += 1
        self._log.warning("tcp listener %s rejected %s: %s", self._uri, peer, reason)


class _Refusal(asyncio.Protocol):
    """Closes a connection over ``max_connections`` as soon as it is made: no buffer, no handshake, no timer."""

    def __init__(self, listener: TcpListener[Any]) -> None:
        self._listener = listener

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        peer = transport.get_extra_info("peername")
        cast(asyncio.Transport, transport).abort()
        limit = self._listener._options.max_connections
        self._listener._count_rejection(str(peer), f"over max_connections={limit}")


def parse_host_port(uri: str, default_host: str, scheme: str = "tcp") -> tuple[str, int]:
    """``SCHEME://HOST:PORT`` -> (HOST or ``default_host``, PORT or 0).

    Raises:
        ConfigError: another scheme, a path, query or fragment, or a port out of range.
    """
    got, _ = split_uri(uri)
    if got != scheme:
        raise ConfigError(f"expected a {scheme}:// URI, got {uri!r}")
    parts = urlsplit(uri)
    if parts.path not in ("", "/") or parts.query or parts.fragment:
        raise ConfigError(f"expected {scheme}://HOST:PORT, got {uri!r}")
    try:
        port = parts.port or 0
    except ValueError as exc:
        raise ConfigError(f"expected {scheme}://HOST:PORT with a port in 0..65535, got {uri!r}") from exc
    return parts.hostname or default_host, port


def format_uri(host: str, port: int, scheme: str = "tcp") -> str:
    """The URI of (host, port), an IPv6 host in brackets."""
    return f"{scheme}://[{host}]:{port}" if ":" in host else f"{scheme}://{host}:{port}"


async def open_listener(
    uri: str, options: TransportOptions, cls: AcceptedEnd[_E], ssl_context: ssl.SSLContext | None = None
) -> TcpListener[_E]:
    """``listen`` for ``cls``'s scheme, with TLS when ``ssl_context`` is given (``tls.listen`` uses it)."""
    host, port = parse_host_port(uri, options.bind_host, cls.scheme)
    if ssl_context is None:
        check_exposure(
            uri,
            host,
            authenticated=options.auth_key is not None,
            insecure=options.insecure,
            how="Set an auth_key (TransportOptions(auth_key=...); `uniros robot serve`: $UNIROS_AUTH_KEY or "
            "--auth-key-env) or use tls:// with client certificates",
        )
    lst = TcpListener[_E](options)
    loop = asyncio.get_running_loop()
    server = await loop.create_server(
        lambda: lst._protocol(lambda: cls(options, listener=lst)),
        host,
        port,
        reuse_address=True,
        ssl=ssl_context,
        ssl_handshake_timeout=options.handshake_timeout_s if ssl_context is not None else None,
    )
    lst._server = server
    sockname = server.sockets[0].getsockname()
    lst._address = (sockname[0], sockname[1])
    lst._uri = format_uri(sockname[0], sockname[1], cls.scheme)
    return lst
