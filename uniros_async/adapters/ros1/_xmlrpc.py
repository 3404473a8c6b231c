"""XML-RPC over asyncio streams: the client side for master and slave API calls, and a minimal HTTP server for our
slave API. ``xmlrpc.client`` only (de)serializes; sockets stay on the event loop, so a call is cancellable and a dead
peer costs at most the caller's timeout.
"""

from __future__ import annotations

import asyncio
import logging
import xmlrpc.client
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit
from xml.parsers.expat import ExpatError

from uniros_async._log_throttle import LogThrottle

__all__ = ["XmlRpcCallError", "XmlRpcServer", "call", "call_ros"]

logger = logging.getLogger(__name__)

_MAX_BODY_BYTES = 16 << 20


class XmlRpcCallError(OSError):
    """The peer answered, but not with an XML-RPC response (bad HTTP status, malformed body) or with a fault."""


def _split_uri(uri: str) -> tuple[str, int, str]:
    parts = urlsplit(uri)
    if parts.scheme != "http" or not parts.hostname:
        raise ValueError(f"expected an http://host:port/ XML-RPC URI, got {uri!r}")
    return parts.hostname, parts.port or 80, parts.path or "/"


async def _read_http_message(reader: asyncio.StreamReader) -> tuple[str, dict[str, str], bytes]:
    """One HTTP message: (start line, lower-cased headers, body). A body without Content-Length runs to EOF."""
    head = await reader.readuntil(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {}
    for line in lines[1:]:
        key, sep, value = line.partition(":")
        if sep:
            headers[key.strip().lower()] = value.strip()
    if "content-length" in headers:
        n = int(headers["content-length"])
        if not 0 <= n <= _MAX_BODY_BYTES:
            raise XmlRpcCallError(f"HTTP Content-Length {n} out of range")
        body = await reader.readexactly(n)
    elif headers.get("transfer-encoding", "").lower() == "chunked":
        raise XmlRpcCallError("chunked HTTP bodies are not supported")
    else:
        body = await reader.read(_MAX_BODY_BYTES)
    return lines[0], headers, body


async def call(uri: str, method: str, *params: Any, timeout_s: float) -> Any:
    """Call ``method(*params)`` at the XML-RPC server ``uri`` and return its result.

    Raises:
        TimeoutError: no complete answer within ``timeout_s``.
        OSError: the connection failed (ConnectionRefusedError, ...), or the answer was not XML-RPC
            (XmlRpcCallError, also for a fault).
    """
    host, port, path = _split_uri(uri)
    request = xmlrpc.client.dumps(params, method, allow_none=True).encode()
    async with asyncio.timeout(timeout_s):
        reader, writer = await asyncio.open_connection(host, port)
        try:
            writer.write(
                f"POST {path} HTTP/1.1\r\nHost: {host}:{port}\r\nUser-Agent: uniros_async\r\n"
                f"Content-Type: text/xml\r\nContent-Length: {len(request)}\r\nConnection: close\r\n\r\n".encode()
                + request
            )
            await writer.drain()
            status, _, body = await _read_http_message(reader)
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, ValueError) as exc:
            raise XmlRpcCallError(f"{uri} {method}: malformed HTTP answer ({exc})") from exc
        finally:
            writer.close()
            try:
                await writer.wait_closed()
            except OSError:
                pass
    if status.split(" ")[1:2] != ["200"]:
        raise XmlRpcCallError(f"{uri} {method}: HTTP status {status!r}")
    try:
        (result,), _ = xmlrpc.client.loads(body)
    except xmlrpc.client.Fault as exc:
        raise XmlRpcCallError(f"{uri} {method}: XML-RPC fault {exc.faultCode}: {exc.faultString}") from exc
    except (xmlrpc.client.ResponseError, ExpatError, ValueError, TypeError) as exc:
        raise XmlRpcCallError(f"{uri} {method}: malformed XML-RPC answer ({exc!r})") from exc
    return result


async def call_ros(uri: str, method: str, *params: Any, timeout_s: float) -> tuple[int, str, Any]:
    """``call`` for the ROS master and slave APIs, whose every answer is ``[code, status message, value]``.

    Raises:
        TimeoutError, OSError: as ``call``; XmlRpcCallError also when the answer is not such a triple.
    """
    result = await call(uri, method, *params, timeout_s=timeout_s)
    if not (isinstance(result, list | tuple) and len(result) == 3 and isinstance(result[0], int)):
        raise XmlRpcCallError(f"{uri} {method}: expected [code, message, value], got {result!r:.200}")
    return int(result[0]), str(result[1]), result[2]


_handler_log = LogThrottle(logger)  # any client can make a handler fail: one warning a second


class XmlRpcServer:
    """Serves XML-RPC methods over HTTP/1.1 POST on an asyncio server (one request per connection).

    ``spawn`` starts each connection's handler as a task of the owner's TaskGroup (so every task has an owner).
    A method is ``handler(*params) -> result``; an unknown method or a handler error is an XML-RPC fault.
    """

    def __init__(self, methods: dict[str, Callable[..., Any]], spawn: Callable[[Any], asyncio.Task[None]]) -> None:
        self._methods = methods
        self._spawn = spawn
        self._server: asyncio.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()
        self._closed = False

    async def start(self, host: str) -> int:
        """Listen on ``host`` at a free port; returns the port."""
        self._server = await asyncio.start_server(self._on_connect, host, 0)
        return int(self._server.sockets[0].getsockname()[1])

    def _on_connect(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self._closed:  # accepted in the same loop turn as close(): no new task may outlive the owner
            writer.close()
            return
        self._writers.add(writer)
        self._spawn(self._serve(reader, writer))

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            async with asyncio.timeout(30.0):  # a client that never sends its request must not hold a task forever
                _, _, body = await _read_http_message(reader)
            reply = self._dispatch(body)
            writer.write(
                b"HTTP/1.1 200 OK\r\nServer: uniros_async\r\nContent-Type: text/xml\r\n"
                + f"Content-Length: {len(reply)}\r\nConnection: close\r\n\r\n".encode()
                + reply
            )
            await writer.drain()
        except (OSError, TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, ValueError) as exc:
            logger.debug("XML-RPC connection dropped: %r", exc)
        finally:
            self._writers.discard(writer)
            writer.close()

    def _dispatch(self, body: bytes) -> bytes:
        try:
            params, method = xmlrpc.client.loads(body)
        # xmlrpc.client raises IndexError, KeyError, ... as well as its own errors on malformed documents
        except (xmlrpc.client.ResponseError, ExpatError, ValueError, TypeError, IndexError, KeyError) as exc:
            return xmlrpc.client.dumps(xmlrpc.client.Fault(-32700, f"parse error: {exc}")).encode()
        handler = self._methods.get(method or "")
        if handler is None:
            return xmlrpc.client.dumps(xmlrpc.client.Fault(-32601, f"unknown method {method!r}")).encode()
        try:
            result = handler(*params)
        except Exception as exc:
            _handler_log.warning("XML-RPC %s%r failed: %r", method, params, exc)
            return xmlrpc.client.dumps(xmlrpc.client.Fault(1, f"{method}: {type(exc).__name__}: {exc}")).encode()
        return xmlrpc.client.dumps((result,), methodresponse=True, allow_none=True).encode()

    def close(self) -> None:
        """Stop listening and drop open connections (synchronous, so it also runs under cancellation)."""
        self._closed = True
        if self._server is not None:
            self._server.close()
        for writer in list(self._writers):
            writer.close()
        self._writers.clear()
