"""TCPROS framing: connection headers and length-prefixed message frames (wiki.ros.org/ROS/TCPROS).

A connection header is a uint32 LE total length, then per field a uint32 LE length and ``key=value`` bytes. After
the headers each message travels as a uint32 LE length and the serialized body.
"""

from __future__ import annotations

import asyncio
import socket
import struct

from uniros_async.errors import CodecError

__all__ = [
    "MAX_FRAME_BYTES",
    "MAX_HEADER_BYTES",
    "decode_header",
    "encode_header",
    "frame",
    "read_frame",
    "read_header",
    "set_nodelay",
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


async def read_frame(reader: asyncio.StreamReader) -> bytes:
    """Read one message body (the length prefix is stripped).

    Raises:
        asyncio.IncompleteReadError: the peer closed the connection (at a frame boundary: ``partial`` is empty).
        CodecError: the length prefix is over MAX_FRAME_BYTES.
    """
    n = await _read_length(reader, MAX_FRAME_BYTES, "frame")
    return await reader.readexactly(n)


def frame(body: bytes) -> bytes:
    """``body`` with its 4-byte length prefix."""
    return _U32.pack(len(body)) + body


def set_nodelay(writer: asyncio.StreamWriter) -> None:
    """TCP_NODELAY: small control messages must not wait for Nagle's algorithm."""
    sock = writer.get_extra_info("socket")
    if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
