"""TCPROS framing: connection headers and length-prefixed message frames (wiki.ros.org/ROS/TCPROS).

A connection header is a uint32 LE total length, then per field a uint32 LE length and ``key=value`` bytes. After
the headers each message travels as a uint32 LE length and the serialized body.
"""

from __future__ import annotations

import asyncio
import fcntl
import socket
import struct
import termios
from collections.abc import Callable

from uniros_async.errors import CodecError
from uniros_async.transports.tcp import set_keepalive

__all__ = [
    "FrameReader",
    "MAX_FRAME_BYTES",
    "MAX_HEADER_BYTES",
    "abort",
    "decode_header",
    "encode_header",
    "frame",
    "read_header",
    "tune_socket",
    "unacked_bytes",
]

_U32 = struct.Struct("<I")
MAX_HEADER_BYTES = 1 << 20  # a full_text is a few kB; a larger header is garbage, not a peer
MAX_FRAME_BYTES = 256 << 20  # a camera image is a few MB; beyond this the length prefix is corrupt


def encode_header(fields: dict[str, str]) -> bytes:
    """A connection header, with its own 4-byte length prefix."""
    parts = []
    for key, value in fields.items():
        item = f"{key}={value}".encode()
        parts.append(_U32.pack(len(item)))
        parts.append(item)
    body = b"".join(parts)
    return _U32.pack(len(body)) + body


def decode_header(body: bytes) -> dict[str, str]:
    """The fields of a connection header body (without its length prefix).

    Raises:
        CodecError: a field length runs past the end, or a field has no ``=``.
    """
    fields: dict[str, str] = {}
    pos = 0
    while pos < len(body):
        if pos + 4 > len(body):
            raise CodecError(f"TCPROS header: {len(body) - pos} stray bytes at byte {pos}")
        (n,) = _U32.unpack_from(body, pos)
        pos += 4
        if pos + n > len(body):
            raise CodecError(f"TCPROS header: a field of {n} bytes at byte {pos} runs past the {len(body)}-byte header")
        key, sep, value = body[pos : pos + n].decode(errors="replace").partition("=")
        if not sep:
            raise CodecError(f"TCPROS header: field {key[:40]!r} at byte {pos} has no '='")
        fields[key] = value
        pos += n
    return fields


async def _read_length(reader: asyncio.StreamReader, limit: int, what: str) -> int:
    (n,) = _U32.unpack(await reader.readexactly(4))
    if n > limit:
        raise CodecError(f"TCPROS {what} announces {n} bytes, more than the limit of {limit}")
    return int(n)


async def read_header(reader: asyncio.StreamReader) -> dict[str, str]:
    """Read one connection header.

    Raises:
        asyncio.IncompleteReadError: the peer closed the connection first.
        CodecError: the header is malformed or longer than MAX_HEADER_BYTES.
    """
    n = await _read_length(reader, MAX_HEADER_BYTES, "header")
    return decode_header(await reader.readexactly(n))


def frame(body: bytes) -> bytes:
    """``body`` with its 4-byte length prefix."""
    return _U32.pack(len(body)) + body


def tune_socket(writer: asyncio.StreamWriter | asyncio.BaseTransport) -> None:
    """TCP_NODELAY (small control messages must not wait for Nagle's algorithm) and keepalive (a subscriber only
    reads: without probes it never learns that a reset reached only its publisher, and never reconnects)."""
    sock = writer.get_extra_info("socket")
    if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        set_keepalive(sock)


_SIOCOUTQ = termios.TIOCOUTQ  # Linux: the same request number on a socket (socket(7))
_LINGER_RESET = struct.pack("ii", 1, 0)


def unacked_bytes(transport: asyncio.BaseTransport) -> int:
    """Bytes of a tcp connection's kernel send queue its peer has not acknowledged yet (``SIOCOUTQ``: sent and
    unacknowledged, plus not sent yet); 0 when the transport has no tcp socket."""
    sock = transport.get_extra_info("socket")
    if sock is None or sock.family not in (socket.AF_INET, socket.AF_INET6) or sock.fileno() < 0:
        return 0
    buf = fcntl.ioctl(sock.fileno(), _SIOCOUTQ, b"\0\0\0\0")
    return int(struct.unpack("i", buf)[0])


def abort(transport: asyncio.BaseTransport) -> None:
    """Close a connection with a reset, discarding whatever it has not delivered: ``SO_LINGER`` 0 makes the kernel
    drop its send queue and send RST (a plain close keeps retransmitting the queue after the close), and
    ``transport.abort()`` drops the event loop's own buffer."""
    sock = transport.get_extra_info("socket")
    if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6) and sock.fileno() >= 0:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, _LINGER_RESET)
    if isinstance(transport, asyncio.WriteTransport):
        transport.abort()
    else:
        transport.close()


class FrameReader(asyncio.Protocol):
    """A subscriber's TCPROS connection, read by the event loop itself: ``header()`` awaits the publisher's
    connection header; after ``start(on_frame)`` every message body goes to ``on_frame`` from ``data_received``, in
    the loop's own callback, so no task has to wake for each message (a StreamReader's reading task costs one
    event-loop round per message). ``wait_closed()`` returns when the connection ends.

    Frames that arrive with the header wait in the buffer until ``start``. ``on_frame`` must not raise.
    """

    def __init__(self) -> None:
        loop = asyncio.get_running_loop()
        self.transport: asyncio.Transport | None = None
        self._buf = bytearray()
        self._header: asyncio.Future[dict[str, str]] = loop.create_future()
        self._closed: asyncio.Future[None] = loop.create_future()
        self._on_frame: Callable[[bytes], None] | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        buf = self._buf
        buf += data
        try:
            while len(buf) >= 4:
                (n,) = _U32.unpack_from(buf)
                if not self._header.done():
                    if n > MAX_HEADER_BYTES:
                        raise CodecError(f"TCPROS header announces {n} bytes, over the limit of {MAX_HEADER_BYTES}")
                    if len(buf) < 4 + n:
                        return
                    fields = decode_header(bytes(buf[4 : 4 + n]))
                    del buf[: 4 + n]
                    self._header.set_result(fields)
                    continue
                if self._on_frame is None:
                    return  # frames wait for start()
                if n > MAX_FRAME_BYTES:
                    raise CodecError(f"TCPROS frame announces {n} bytes, over the limit of {MAX_FRAME_BYTES}")
                if len(buf) < 4 + n:
                    return
                body = bytes(buf[4 : 4 + n])
                del buf[: 4 + n]
                self._on_frame(body)
        except CodecError as exc:
            self._fail(exc)

    def _fail(self, exc: BaseException) -> None:
        for fut in (self._header, self._closed):
            if not fut.done():
                fut.set_exception(exc)
        if self.transport is not None:
            self.transport.close()

    def start(self, on_frame: Callable[[bytes], None]) -> None:
        """Hand every frame, from now on and those already here, to ``on_frame``."""
        self._on_frame = on_frame
        if self._buf:
            self.data_received(b"")

    async def header(self) -> dict[str, str]:
        """The publisher's connection header.

        Raises:
            asyncio.IncompleteReadError: the peer closed the connection first.
            CodecError: the header is malformed or longer than MAX_HEADER_BYTES.
        """
        return await asyncio.shield(self._header)

    async def wait_closed(self) -> None:
        """Return when the connection ends.

        Raises:
            asyncio.IncompleteReadError: the peer closed it.
            OSError: it failed.
            CodecError: a frame's length prefix was corrupt.
        """
        await asyncio.shield(self._closed)

    def connection_lost(self, exc: Exception | None) -> None:
        eof = asyncio.IncompleteReadError(bytes(self._buf), None)
        for fut in (self._header, self._closed):
            if not fut.done():
                fut.set_exception(exc if exc is not None else eof)
        for fut in (self._header, self._closed):  # nobody may be waiting any more: no "never retrieved" warnings
            if fut.done() and not fut.cancelled():
                fut.exception()
