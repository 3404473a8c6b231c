"""In-process transport: the reference implementation of the Transport contract and the test double.

``memory://NAME`` listeners live in a per-process table. Frames are copied once on send (so a sender may reuse its
buffer at once, as on every other transport) and handed to the receiver as a memoryview of that copy. A bounded
inbox gives backpressure: ``send`` waits while the peer has ``inbox_frames`` frames unread.

The bus does not use this for in-process pub/sub (there subscribers get the message object itself, no encoding);
it exists so that every layer above transports can be tested without sockets, and to define the contract.
"""

from __future__ import annotations

import asyncio
import collections
import itertools
from collections.abc import Sequence

from uniros_async.backoff import Backoff
from uniros_async.errors import ConfigError, FrameTooLargeError, TransportBrokenError, TransportClosedError
from uniros_async.transports.base import Buffer, Delivery, Listener, Transport, TransportOptions, frame_nbytes

__all__ = ["MemoryListener", "MemoryTransport", "connect", "listen"]

_LISTENERS: dict[str, MemoryListener] = {}
_anon = itertools.count()


class MemoryTransport(Transport):
    """One end of an in-process pair.

    The inbox is a bounded deque; closing is a flag beside it, never an item in it, so a close can neither wait
    for room nor push out a frame the peer already accepted.
    """

    delivery = Delivery.RELIABLE
    scheme = "memory"

    def __init__(self, name: str, options: TransportOptions, inbox_frames: int = 1024) -> None:
        super().__init__()
        self._name = name
        self._options = options
        self._inbox: collections.deque[bytes] = collections.deque()
        self._inbox_frames = inbox_frames
        self._readable = asyncio.Event()  # set: a frame arrived, or this end / the peer closed
        self._writable = asyncio.Event()  # set: the peer took a frame, or either end closed
        self._peer: MemoryTransport | None = None
        self._closed = False
        self._peer_closed = False

    @property
    def max_frame_bytes(self) -> int:
        return self._options.max_frame_bytes

    @property
    def peer(self) -> str:
        return f"memory://{self._name}"

    async def send(self, frame: Buffer | Sequence[Buffer]) -> None:
        n = frame_nbytes(frame)
        if n > self._options.max_frame_bytes:
            raise FrameTooLargeError(f"frame of {n} bytes exceeds max_frame_bytes={self._options.max_frame_bytes}")
        data = bytes(frame) if isinstance(frame, bytes | bytearray | memoryview) else b"".join(frame)
        while True:
            if self._closed:
                raise TransportClosedError(f"send on closed transport to {self.peer}")
            peer = self._peer
            if peer is None or self._peer_closed:
                raise TransportBrokenError(f"peer {self.peer} closed the connection")
            if len(peer._inbox) < peer._inbox_frames:
                break
            self._writable.clear()
            await self._writable.wait()  # backpressure: the peer has inbox_frames unread
        peer._inbox.append(data)
        peer._readable.set()
        self.stats.frames_sent += 1
        self.stats.bytes_sent += n

    async def receive(self) -> memoryview:
        while True:
            if self._closed:
                raise TransportClosedError(f"transport to {self.peer} was closed")
            if self._inbox:
                data = self._inbox.popleft()
                if self._peer is not None:
                    self._peer._writable.set()
                self.stats.frames_received += 1
                self.stats.bytes_received += len(data)
                return memoryview(data)
            if self._peer_closed:  # only after every frame the peer sent was delivered
                raise TransportBrokenError(f"peer {self.peer} closed the connection")
            self._readable.clear()
            await self._readable.wait()

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._readable.set()
        self._writable.set()
        peer = self._peer
        if peer is not None:
            peer._peer_closed = True
            peer._readable.set()
            peer._writable.set()


class MemoryListener(Listener):
    """Accepts in-process connections at ``memory://NAME``."""

    def __init__(self, name: str, options: TransportOptions) -> None:
        self._name = name
        self._options = options
        self._pending: asyncio.Queue[MemoryTransport | None] = asyncio.Queue()
        self._closed = False

    @property
    def uri(self) -> str:
        return f"memory://{self._name}"

    async def accept(self) -> Transport:
        if self._closed:
            raise TransportClosedError(f"listener {self.uri} is closed")
        t = await self._pending.get()
        if t is None:
            raise TransportClosedError(f"listener {self.uri} is closed")
        return t

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        _LISTENERS.pop(self._name, None)
        self._pending.put_nowait(None)


async def listen(uri: str, options: TransportOptions) -> MemoryListener:
    """Listen at ``memory://NAME`` (an empty NAME picks a unique one).

    Raises:
        ConfigError: NAME is already taken in this process.
    """
    name = uri.split("://", 1)[1] or f"anon-{next(_anon)}"
    if name in _LISTENERS:
        raise ConfigError(f"memory://{name} is already listening in this process")
    lst = MemoryListener(name, options)
    _LISTENERS[name] = lst
    return lst


async def connect(uri: str, options: TransportOptions) -> MemoryTransport:
    """Connect to ``memory://NAME``, waiting (with backoff) up to ``connect_timeout_s`` for it to appear."""
    name = uri.split("://", 1)[1]
    backoff = Backoff(first_s=0.001, max_s=0.1)
    async with asyncio.timeout(options.connect_timeout_s):
        while (lst := _LISTENERS.get(name)) is None or lst._closed:
            await backoff.sleep()
    a = MemoryTransport(name, options)
    b = MemoryTransport(name, lst._options)
    a._peer, b._peer = b, a
    lst._pending.put_nowait(b)
    return a
