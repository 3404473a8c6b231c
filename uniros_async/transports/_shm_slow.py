"""The slow paths of a ``shm://`` connection (``ShmTransport``): what ``RingEnd``'s fast paths leave to Python.

- A skip record: a writer that finds too little room before the ring's end writes one and starts the frame at
  offset 0; the reader jumps over it.
- A frame that wraps around the ring's end: ``receive`` returns a copy of it instead of a view into the ring.
- A frame larger than the ring: streamed through it in chunks (a quarter of the ring at most each), which needs the
  peer to be receiving meanwhile, as on TCP. The reader collects the chunks in a buffer of its own. A send cancelled
  half-way finishes the rest in the background from a copy, so that no half frame is ever left in the ring.
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from typing import TYPE_CHECKING

from uniros_async.errors import TransportBrokenError
from uniros_async.transports._shm_ring import R_POS, SKIP, RingViews
from uniros_async.transports.base import Buffer

if TYPE_CHECKING:
    from uniros_async.transports._shm_ring import RingEnd
    from uniros_async.transports.base import TransportStats

__all__ = ["Partial", "ShmSlowPaths", "as_parts"]


class ShmSlowPaths:
    """The slow paths of ``ShmTransport`` (its base): skip records, wrapped frames, streamed frames."""

    # the connection's state they share (ShmTransport sets it)
    stats: TransportStats
    _loop: asyncio.AbstractEventLoop
    _cap: int
    _max_frame: int
    _ring: RingEnd
    _rx: RingViews
    _tx: RingViews
    _rx_partial: Partial | None
    _tx_stream: asyncio.Task[None] | None
    _broken: str | None
    _closed: bool
    _peer_gone: bool

    # provided by ShmTransport
    @property
    def peer(self) -> str:
        raise NotImplementedError

    def _fail(self, reason: str) -> TransportBrokenError:
        raise NotImplementedError

    async def _wait_writable(self, need: int) -> None:
        raise NotImplementedError

    def _take(self, avail: int) -> memoryview | None:
        """Consume what ``avail`` bytes allow: a whole frame (returned), a skip record or a streamed chunk (None)."""
        cap = self._cap
        ring = self._ring
        rpos = ring.rpos
        if avail > cap or avail < 0:
            raise self._fail(f"ring from {self.peer} holds {avail} bytes, more than its capacity {cap}")
        if self._rx_partial is not None:
            return self._take_chunk(avail)
        off = rpos % cap
        n = self._rx.data_q[off >> 3]
        if n & SKIP:
            if n != SKIP or avail < cap - off:
                raise self._fail(f"bad skip record from {self.peer}")
            ring.rpos = rpos + cap - off
            return None
        if n > self._max_frame:
            self.stats.rejected += 1
            raise self._fail(f"peer {self.peer} announced a frame of {n} bytes, over max_frame_bytes={self._max_frame}")
        padded = (n + 7) & ~7
        if 8 + padded > cap:  # streamed: collect the chunks in a buffer of our own
            self._rx_partial = Partial(n, padded)
            ring.rx_fast = False
            ring.rpos = rpos + 8
            ring.release_rx()
            return None
        if avail < 8 + padded:
            raise self._fail(f"truncated record from {self.peer}: {avail} bytes of {8 + padded}")
        start = off + 8
        if start == cap:
            start = 0
        end = start + n
        ring.rpos = rpos + 8 + padded
        ring.frames_received += 1
        ring.bytes_received += n
        if end <= cap:
            return self._rx.data_ro[start:end]  # zero-copy; released at the next receive()
        buf = bytearray(n)
        first = cap - start
        data = self._rx.data
        buf[:first] = data[start:]
        buf[first:] = data[: n - first]
        ring.release_rx()
        return memoryview(buf).toreadonly()

    def _take_chunk(self, avail: int) -> memoryview | None:
        part = self._rx_partial
        assert part is not None
        ring = self._ring
        take = min(avail, part.padded - part.got)
        lo, hi = part.got, min(part.got + take, part.n)
        if hi > lo:  # the rest of the chunk is padding
            cap = self._cap
            data = self._rx.data
            dst = part.view
            pos = ring.rpos % cap
            first = min(hi - lo, cap - pos)
            dst[lo : lo + first] = data[pos : pos + first]
            if first < hi - lo:
                dst[lo + first : hi] = data[: hi - lo - first]
        part.got += take
        ring.rpos += take
        ring.release_rx()
        if part.got < part.padded:
            return None
        self._rx_partial = None
        ring.rx_fast = self._broken is None and not self._closed
        ring.frames_received += 1
        ring.bytes_received += part.n
        return part.view.toreadonly()

    async def _send_streamed(self, parts: Sequence[Buffer], n: int) -> None:
        out = _Outgoing([p if type(p) is memoryview else memoryview(p) for p in parts if len(p)], n)
        try:
            await self._stream(out)
        except asyncio.CancelledError:
            if out.header_sent and out.left:
                # A half-sent frame would poison the stream: finish it from a copy (the caller may reuse its
                # buffers once we return), in a task that aclose() cancels.
                out.detach()
                self._tx_stream = self._loop.create_task(self._stream(out), name=f"{self.peer} stream rest")
                self._ring.tx_fast = False
                self._tx_stream.add_done_callback(_retrieve)
            raise

    async def _stream(self, out: _Outgoing) -> None:
        cap = self._cap
        ctl = self._tx.ctl
        data = self._tx.data
        ring = self._ring
        while out.left:
            free = cap - (ring.wpos - ctl[R_POS])
            need = 8 if not out.header_sent else min(cap // 4, out.left)
            if free < need:
                if self._peer_gone:
                    raise TransportBrokenError(f"peer {self.peer} closed the connection")
                await self._wait_writable(need)
                continue
            wpos = ring.wpos
            if not out.header_sent:
                self._tx.data_q[(wpos % cap) >> 3] = out.n
                wpos += 8
                free -= 8
                out.header_sent = True
            k = min(free, out.left)
            out.copy_into(data, wpos % cap, k)
            ring.publish(wpos + k)
        ring.sent_since_wait += out.n
        ring.frames_sent += 1
        ring.bytes_sent += out.n

    async def _join_stream(self) -> None:
        """Wait for a streamed frame whose send was cancelled to be finished in the background."""
        task = self._tx_stream
        assert task is not None
        await asyncio.wait({task})  # not cancelled with us: the frame must be finished before the next one
        self._tx_stream = None  # its error, if any, left state (peer gone, closed) that send() reports
        self._ring.tx_fast = not (self._closed or self._broken is not None or self._peer_gone)


class Partial:
    """A streamed frame being received."""

    __slots__ = ("got", "n", "padded", "view")

    def __init__(self, n: int, padded: int) -> None:
        self.n = n
        self.padded = padded
        self.got = 0
        self.view = memoryview(bytearray(n))


class _Outgoing:
    """A streamed frame being sent: the parts still to copy, then padding."""

    __slots__ = ("header_sent", "left", "n", "parts")

    def __init__(self, parts: list[memoryview], n: int) -> None:
        self.parts = parts
        self.n = n
        self.left = (n + 7) & ~7  # payload and padding still to publish
        self.header_sent = False

    def copy_into(self, data: memoryview, pos: int, k: int) -> None:
        cap = len(data)
        self.left -= k
        while k:
            if pos == cap:
                pos = 0
            room = min(k, cap - pos)
            if self.parts:
                src = self.parts[0]
                take = min(room, len(src))
                data[pos : pos + take] = src[:take]
                if take == len(src):
                    self.parts.pop(0)
                else:
                    self.parts[0] = src[take:]
            else:
                take = room  # padding: whatever the ring holds
            pos += take
            k -= take

    def detach(self) -> None:
        """Copy what is left, so the caller's buffers are no longer needed."""
        self.parts = [memoryview(b"".join(self.parts))] if self.parts else []


def as_parts(frame: Buffer | Sequence[Buffer]) -> Sequence[Buffer]:
    """Buffers that memoryview slice assignment accepts (1-D, unsigned bytes), whatever the caller passed."""
    if isinstance(frame, bytes | bytearray):
        return (frame,)
    if isinstance(frame, memoryview):
        return (_flat(frame),)
    return [_flat(memoryview(p)) for p in frame]


def _flat(view: memoryview) -> memoryview:
    if view.format == "B" and view.ndim == 1:
        return view
    if view.c_contiguous:
        return view.cast("B")
    return memoryview(view.tobytes())


def _retrieve(task: asyncio.Task[None]) -> None:
    if not task.cancelled():
        task.exception()  # consumed here; send() reports the state it left
