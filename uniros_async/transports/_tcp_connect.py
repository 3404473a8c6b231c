"""Opening a ``tcp://`` or ``tls://`` connection: dial, retry with backoff while the listener starts or is full,
and wait for the uniros handshake (``TcpTransport``'s), all within ``connect_timeout_s``. ``tcp.connect`` and
``tls.connect`` call it with their transport class."""

from __future__ import annotations

import asyncio
import ssl
from typing import Protocol, TypeVar

from uniros_async.backoff import Backoff
from uniros_async.errors import AuthenticationError, ConfigError, TransportBrokenError
from uniros_async.transports._tcp_listener import parse_host_port
from uniros_async.transports._tcp_receive import TcpReceiving
from uniros_async.transports.base import TransportOptions

_E = TypeVar("_E", bound=TcpReceiving)
_E_co = TypeVar("_E_co", bound=TcpReceiving, covariant=True)


class ConnectingEnd(Protocol[_E_co]):
    """The class of the end ``open_connection`` makes (``tcp.TcpTransport``, ``tls.TlsTransport``), passed in so
    that this module does not import the transport that imports it."""

    @property
    def scheme(self) -> str: ...

    def __call__(self, options: TransportOptions, *, uri: str) -> _E_co: ...


__all__ = ["ConnectingEnd", "open_connection"]


async def open_connection(
    uri: str, options: TransportOptions, cls: ConnectingEnd[_E], ssl_context: ssl.SSLContext | None = None
) -> _E:
    """``connect`` for ``cls``'s scheme, with TLS when ``ssl_context`` is given (``tls.connect`` uses it)."""
    host, port = parse_host_port(uri, "", cls.scheme)
    if not host or not port:
        raise ConfigError(f"connect needs {cls.scheme}://HOST:PORT with a nonzero port, got {uri!r}")
    loop = asyncio.get_running_loop()
    timeout_s = options.connect_timeout_s
    deadline = loop.time() + timeout_s
    backoff = Backoff(first_s=0.005, max_s=0.5)
    last: Exception | None = None
    while True:
        try:
            async with asyncio.timeout_at(deadline):
                _, t = await loop.create_connection(
                    lambda: cls(options, uri=uri),
                    host,
                    port,
                    ssl=ssl_context,
                    server_hostname=host if ssl_context is not None else None,
                )
        except TimeoutError:
            raise TimeoutError(f"could not connect to {uri} within {timeout_s} s (last error: {last})") from last
        except ssl.SSLError as exc:  # a certificate refused: retrying cannot help
            raise AuthenticationError(f"TLS handshake with {uri} failed: {exc}") from exc
        except OSError as exc:  # refused while the listener starts, unreachable, ... : retry until the deadline
            last = exc
        else:
            try:
                async with asyncio.timeout_at(deadline):
                    await asyncio.shield(t._ready)
                return t
            except TimeoutError as exc:
                await t.aclose()
                raise TimeoutError(
                    f"{uri} accepted the connection but did not complete the handshake within {timeout_s} s"
                ) from exc
            except TransportBrokenError as exc:
                await t.aclose()
                if not t._hs_dropped:
                    raise
                # The listener hung up mid-handshake: it is at max_connections, or evicted us among too many
                # unfinished handshakes (a burst of connections). Both pass: retry until the deadline.
                last = exc
            except BaseException:
                await t.aclose()
                raise
        remaining = deadline - loop.time()
        if remaining <= 0:
            raise TimeoutError(f"could not connect to {uri} within {timeout_s} s (last error: {last})") from last
        await backoff.sleep(limit_s=remaining)
