"""The receiving side of a ``tcp://`` connection (``TcpTransport``): the stream buffer, large frames read into
buffers of their own, the queue of complete frames, and the polling of the socket while an answer is due.

An asyncio.BufferedProtocol reads straight into the connection's stream buffer; frames under 16 KiB are copied out
of it (cheaper than any bookkeeping), larger ones are read straight into a buffer of their own from a
per-connection pool, so an image is copied once (kernel to that buffer) and ``receive`` returns a view of it. A pool
buffer is reused only once no view of it is alive any more (a caller's, or an event loop still sending it back), so
even views kept past the next ``receive`` stay intact. Complete frames queue in the connection; reading pauses while
more than 8 MiB are queued unread.

Polling (the rule of ``_spin``, which ``ShmTransport`` shares): when this end sent a frame since it last received
one (it may be waiting for an answer), ``receive`` reads the socket itself (``os.readv`` into the same buffers the
loop's reader would use) for up to ``spin_ns`` before it sleeps in the event loop, yielding the CPU between reads;
reading the socket itself, not turning the event loop (which also takes the CPU a peer on the same core needs),
keeps the receiving core awake just long enough. After a large send the window grows by 1 ns per byte sent. A
receiver that only listens never polls: reading each frame as it lands would cost a stream much of its small-frame
rate.

Outside the loop: ``receive_blocking`` reads the socket in the caller's thread (the poll's reads, then ``poll(2)``),
for a caller in the loop's thread while the loop is not running (the supervisor between calls). Whatever it cannot
do it leaves to ``receive``, having taken nothing.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import mmap
import os
import select
import struct
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Protocol, cast

from uniros_async._log_throttle import LogThrottle
from uniros_async.transports._spin import (
    LOOK_EVERY_NS,
    SHARED_CORE_NS,
    SPIN_CREDIT,
    SPIN_EXTRA_NS,
    SpinCredit,
    now_ns,
    peer_cpu,
    spin_yield,
    this_cpu,
)
from uniros_async.transports.base import Transport

if TYPE_CHECKING:
    from uniros_async.transports.base import TransportStats

__all__ = ["RejectionCounter", "TcpReceiving"]

logger = logging.getLogger("uniros_async.transports.tcp")

_HEADER = struct.Struct("<I")
_unpack_header = _HEADER.unpack_from

_STREAM_BYTES = 256 * 1024  # receive buffer of each connection: anonymous memory, only touched pages are resident
_READ_BYTES = 64 * 1024  # at most this much per read into the stream buffer (bounds the copy of a large frame's start)
_SMALL_FRAME_BYTES = 16 * 1024  # smaller frames are copied out of the stream buffer; larger get their own buffer
_POOL_BUFFERS = 16  # large-frame buffers kept for reuse per connection (at most _POOL_BYTES in all)
_POOL_BYTES = 16 * 1024 * 1024
_RX_HIGH_BYTES = 8 * 1024 * 1024  # pause reading while more than this is queued unread
_RX_LOW_BYTES = 2 * 1024 * 1024  # resume below this
_HANG_UP = getattr(select, "POLLRDHUP", 0x2000)  # poll(2): the peer closed its end (POLLHUP, POLLERR: always reported)
_HANDSHAKE, _FRAMES, _DEAD = 0, 1, 2  # the connection's states (TcpTransport._state)

_now_ns = now_ns  # module globals: a spin reads them every poll
_SPIN_CREDIT = SPIN_CREDIT
_SPIN_EXTRA_NS = SPIN_EXTRA_NS
_yield = spin_yield
_this_cpu = this_cpu

_client_log = LogThrottle(logger)


def _unexported(buf: bytearray) -> bool:
    """True if no memoryview of ``buf`` is alive (CPython refuses to resize an exported bytearray).

    Pool buffers are allocated one byte longer than their length, so this append/delete never reallocates.
    """
    try:
        buf.append(0)
    except BufferError:
        return False
    del buf[-1]
    return True


class RejectionCounter(Protocol):
    """What a connection tells the listener that accepted it (``_tcp_listener.TcpListener``) when it refuses
    its peer."""

    def _count_rejection(self, peer: str, reason: str) -> None: ...


class TcpReceiving(SpinCredit, asyncio.BufferedProtocol, Transport):
    """The receive side of ``TcpTransport`` (its base): the asyncio protocol's reading callbacks, ``receive`` and
    ``receive_blocking``. The connection (handshake, sending, life cycle) is ``TcpTransport``'s."""

    spin_ns: int = 50_000
    """When ``receive`` may be waiting for an answer (this end sent a frame since it last received one), it reads
    the socket itself for up to this long before it sleeps in the event loop, yielding the CPU between reads, while
    spins keep finding frames (``_spin.SpinCredit``). A receiver that only listens (a subscriber, the far end of a
    stream) never polls: it sleeps and reads what piled up in one go. Set it on the class or on one transport; 0
    always sleeps (a real-time worker's connections do: a SCHED_RR process that polls keeps lower-ranked ones from
    their cores)."""

    peer_pid: int | None = None
    """The peer's process id when it runs on this host (a worker sets its agent's): a poll that lasts half its
    window looks whether the peer runs on this core, and if so calls ``on_shared_core`` (``_peer_here``)."""
    on_shared_core: Callable[[int], None] | None = None
    """With ``peer_pid``: called with this core when the peer was found on it, to move this end elsewhere (a worker
    moves itself, ``runtime.worker``), as ``ShmTransport.on_shared_core``."""

    # the connection's state that reading shares (TcpTransport sets it)
    stats: TransportStats
    _loop: asyncio.AbstractEventLoop
    _tr: asyncio.Transport | None
    _listener: RejectionCounter | None
    _ready: asyncio.Future[None]  # the handshake done (client side)
    _hs_started_s: float  # when the listener admitted the handshake (server side)
    _hs_dropped: bool  # the peer hung up during the handshake
    _peer: str
    _recv_limit: int
    _state: int
    _ok: bool
    _closed: bool
    _last_write_s: float

    def _init_receiving(self) -> None:
        # An anonymous mapping, not a bytearray: a bytearray is zero-filled (all 256 KiB resident at once), while
        # a mapping's pages become resident only when data lands in them. A connection that sees small frames
        # (or only a handshake) keeps its reads in the first pages: ~4 KiB resident instead of 256 KiB.
        self._rbuf = mmap.mmap(-1, _STREAM_BYTES)
        self._rview = memoryview(self._rbuf)
        self._rhead = self._rview[:_READ_BYTES]  # what get_buffer hands out when the stream buffer is empty
        self._rpos = 0  # start of unparsed bytes
        self._rend = 0  # end of received bytes
        self._big: memoryview | None = None  # the large frame being read straight into its own buffer
        self._big_got = 0
        self._frames: collections.deque[bytes | memoryview] = collections.deque()
        self._queued = 0  # bytes in _frames
        self._reading_paused = False
        self._rx_waiter: asyncio.Future[None] | None = None
        self._lent: list[bytearray] = []  # large-frame buffers handed out by receive, maybe still in use
        self._pool: list[bytearray] = []
        self._fd = -1  # the socket's descriptor, for receive's own reads while it spins (-1: none, or lost)
        self._spin_credit = _SPIN_CREDIT
        self._spin_allowed = True
        self._next_look_ns = 0  # _peer_here: not before then
        self._sent_since_receive = 0  # bytes: only a receive that may be waiting for an answer polls

    # provided by TcpTransport
    def _raise_unusable(self, op: str) -> None:
        raise NotImplementedError

    def _set_error(self, msg: str, cause: BaseException | None = None) -> None:
        raise NotImplementedError

    def _handshake_data(self) -> None:
        raise NotImplementedError

    def _handshake_failed(self, exc: Exception, cause: BaseException | None = None) -> None:
        raise NotImplementedError

    async def receive(self) -> memoryview:
        """Wait for the next frame; the view is valid until the next ``receive``. Cancelling leaves a frame
        that arrived meanwhile queued for the next call.

        Raises:
            TransportClosedError: our own code closed this end.
            TransportBrokenError: the peer closed the connection (after every complete frame it sent was
                delivered), vanished, or broke the protocol.
        """
        frames = self._frames
        if not frames:
            window_ns = self._poll_for_answer()
            t0 = _now_ns()
            while not frames:
                if not self._ok:
                    self._raise_unusable("receive")
                if self._rx_waiter is not None:
                    raise RuntimeError(f"receive() on {self._peer} while another receive() is waiting")
                fut = self._rx_waiter = self._loop.create_future()
                try:
                    await fut
                finally:
                    self._rx_waiter = None
                self._waited(t0, window_ns)
            # a frame that answers this wait is a reply, not part of a burst: it goes out at once
            self._last_write_s = 0.0
        if self._closed:
            self._raise_unusable("receive")
        return self._pop_frame()

    def _pop_frame(self) -> memoryview:
        """The next queued frame as ``receive`` returns it (there is one)."""
        self._sent_since_receive = 0
        frame = self._frames.popleft()
        if isinstance(frame, bytes):
            n = len(frame)
            view = memoryview(frame)
        else:
            lent = self._lent
            lent.append(cast(bytearray, frame.obj))
            if len(lent) > _POOL_BUFFERS:
                del lent[0]  # held for long by the caller: leave it to the garbage collector
            n = frame.nbytes
            view = frame
        self._queued -= n
        if self._reading_paused and self._queued <= _RX_LOW_BYTES and self._tr is not None:
            self._reading_paused = False
            self._tr.resume_reading()
        stats = self.stats
        stats.frames_received += 1
        stats.bytes_received += n
        return view

    def receive_blocking(self, timeout_s: float, watch: Sequence[int] = ()) -> memoryview | None:
        """``receive`` in the calling thread while the event loop does not run (the agent's thread waiting for its
        workers' replies): a frame already queued, or one read from the socket here (``_spin``'s reads, then
        ``poll(2)`` on the socket for at most ``timeout_s``). Returns None when it cannot be had this way: nothing
        came in time, something is unsent (only the loop sends it), reading is paused, the peer hung up or broke
        the protocol, this end is closed, or one of the sockets in ``watch`` (other connections' descriptors) was
        hung up or reset meanwhile (``poll(2)``'s POLLRDHUP, POLLHUP or POLLERR). Nothing was consumed then:
        ``receive`` must be awaited (it delivers the frame or raises what is wrong)."""
        tr = self._tr
        if tr is None or self._closed or not self._ok or tr.get_write_buffer_size():
            return None
        frames = self._frames
        if not frames:
            fd = self._fd
            if fd < 0:
                return None
            deadline = _now_ns() + int(timeout_s * 1e9)
            window_ns = self._poll_for_answer()
            t0 = _now_ns()
            poller = None
            while not frames:
                left_ns = deadline - _now_ns()
                if left_ns <= 0 or not self._ok or self._reading_paused or self._fd < 0:
                    return None
                if poller is None:
                    poller = select.poll()
                    poller.register(fd, select.POLLIN)
                    for other in watch:
                        poller.register(other, _HANG_UP)
                ready = poller.poll(-(-left_ns // 1_000_000))
                if not ready:
                    continue
                if watch and any(got != fd for got, _ in ready):
                    return None  # another connection hung up: the caller's business first
                try:
                    n = os.readv(fd, (self.get_buffer(-1),))
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError:
                    return None  # the loop's reader meets the error too
                if n == 0:
                    return None  # end of stream: the loop's reader sees it as well
                self.buffer_updated(n)
            self._waited(t0, window_ns)
            self._last_write_s = 0.0  # a frame that answers this wait is a reply, as in receive
        return self._pop_frame()

    def _poll_for_answer(self) -> int:
        """Before a wait: if this end sent since it last received (an answer may be due), poll the socket for up to
        the window (``_spin``, under the spin credit); the window, 0 when none applies."""
        if not (self.spin_ns and self._sent_since_receive):
            return 0
        window_ns = self.spin_ns + min(self._sent_since_receive, _SPIN_EXTRA_NS)  # 1 ns per byte sent
        if self._spin_credit > 0:
            self._spin(window_ns)
        return window_ns

    def get_buffer(self, sizehint: int) -> memoryview:
        if self._big is not None:
            return self._big[self._big_got :]
        end = self._rend
        if not end:
            return self._rhead
        if len(self._rbuf) - end < _READ_BYTES:
            # Move the unparsed tail (less than one small frame plus a header) to the front.
            pos = self._rpos
            self._rview[: end - pos] = self._rview[pos:end]
            end = self._rend = end - pos
            self._rpos = 0
        return self._rview[end : end + _READ_BYTES]

    def buffer_updated(self, nbytes: int) -> None:
        big = self._big
        if big is not None:
            self._big_got += nbytes
            if self._big_got == big.nbytes:
                self._big = None
                self._frames.append(big)
                self._queued += big.nbytes
                self._frames_arrived()
            return
        self._rend += nbytes
        if self._state == _FRAMES:
            self._parse_frames()
        elif self._state == _HANDSHAKE:
            self._handshake_data()

    def _parse_frames(self) -> None:
        buf, view, frames = self._rbuf, self._rview, self._frames
        pos, end = self._rpos, self._rend
        limit = self._recv_limit
        queued = 0
        while end - pos >= 4:
            n = _unpack_header(buf, pos)[0]
            start = pos + 4
            if n < _SMALL_FRAME_BYTES and n <= limit:
                pos = start + n
                if pos > end:
                    pos = start - 4
                    break
                frames.append(view[start:pos].tobytes())
                queued += n
            elif n > limit:
                self._rpos = pos
                self._reject(f"announced a frame of {n} bytes, over max_frame_bytes={limit}")
                return
            else:
                big = self._take_buffer(n)
                got = min(end - start, n)
                big[:got] = view[start : start + got]
                pos = start + got
                if got < n:
                    self._big = big
                    self._big_got = got
                    break
                frames.append(big)
                queued += n
        if pos == end:
            self._rpos = self._rend = 0
        else:
            self._rpos = pos
        if queued or frames:
            self._queued += queued
            w = self._rx_waiter
            if w is not None and not w.done():
                w.set_result(None)
            if self._queued > _RX_HIGH_BYTES and not self._reading_paused:
                self._reading_paused = True
                self._tr.pause_reading()  # type: ignore[union-attr]

    def _frames_arrived(self) -> None:
        w = self._rx_waiter
        if w is not None and not w.done():
            w.set_result(None)
        if self._queued > _RX_HIGH_BYTES and not self._reading_paused and self._tr is not None:
            self._reading_paused = True
            self._tr.pause_reading()

    def _spin(self, window_ns: int) -> None:
        """Read the socket ourselves (the event loop's reader would do the same with the same buffers) until a
        whole frame is queued or ``window_ns`` passed, yielding the CPU between reads. Anything unusual (end of
        stream, an error, paused reading) is left to the event loop, which meets it on its next read. With a
        ``peer_pid``, a spin that lasted half its window (at most ``SHARED_CORE_NS``) looks once where the peer runs
        (``_peer_here``)."""
        fd = self._fd
        if fd < 0 or not self._ok:
            return
        frames = self._frames
        now = _now_ns()
        deadline = now + window_ns
        look_at = now + min(SHARED_CORE_NS, window_ns // 2) if self.peer_pid else deadline
        readv = os.readv
        while not self._reading_paused:
            try:
                n = readv(fd, (self.get_buffer(-1),))
            except (BlockingIOError, InterruptedError):
                now = _now_ns()
                if now > look_at:
                    if now > deadline:
                        self._spin_credit -= 1
                        return
                    look_at = deadline
                    self._peer_here()
                _yield()  # a peer (or anything else) waiting for this core runs now, not after the spin
                continue
            except OSError:
                return
            if n == 0:
                return
            self.buffer_updated(n)
            if frames or not self._ok:
                self._spin_credit = _SPIN_CREDIT
                return

    def _peer_here(self) -> None:
        """If the peer process (``peer_pid``, on this host) last ran on the core this end polls on, have this end
        moved elsewhere (``on_shared_core``); at most once per ``LOOK_EVERY_NS``. ``ShmTransport`` learns where its
        peer runs from their shared page; tcp has none, so it reads ``/proc`` (``_spin.peer_cpu``; the module
        ``_spin`` says why a shared core matters)."""
        now = _now_ns()
        if now < self._next_look_ns or self.on_shared_core is None or self.peer_pid is None:
            return
        self._next_look_ns = now + LOOK_EVERY_NS
        cpu = _this_cpu()
        where = peer_cpu(self.peer_pid)
        if where is None:  # gone, or no /proc here: look no more
            self.peer_pid = None
            return
        if cpu >= 0 and where == cpu:
            self.on_shared_core(cpu)

    def _take_buffer(self, n: int) -> memoryview:
        """A buffer for a large frame: a pooled one that nobody holds any more, or a new one."""
        pool = self._pool
        if self._lent:
            held: list[bytearray] = []
            for buf in self._lent:
                (pool if _unexported(buf) else held).append(buf)
            self._lent = held
            while len(pool) > _POOL_BUFFERS or sum(map(len, pool)) > _POOL_BYTES:
                del pool[0]
        for i, buf in enumerate(pool):
            if n <= len(buf) <= 2 * n:
                del pool[i]
                return memoryview(buf)[:n]
        buf = bytearray(n + 1)  # one spare byte of capacity: see _unexported
        del buf[n:]
        return memoryview(buf)[:n]

    def _reject(self, reason: str) -> None:
        """The peer broke the protocol after the handshake: count it and drop the connection."""
        self.stats.rejected += 1
        if self._listener is not None:
            self._listener._count_rejection(self._peer, reason)
        else:
            _client_log.warning("tcp: dropping connection to %s: it %s", self._peer, reason)
        self._state = _DEAD
        self._big = None
        self._set_error(f"peer {self._peer} {reason}; connection dropped")
        if self._tr is not None:
            self._tr.abort()
