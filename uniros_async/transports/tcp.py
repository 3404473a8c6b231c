"""Network transport: length-prefixed frames over TCP, ``tcp://HOST:PORT``.

Wire format: after the handshake (``_tcp_handshake``: HELLO both ways, then with an ``auth_key`` an HMAC proof
both ways), each frame is ``length(u32, little-endian) payload(length bytes)``. Each side announces its
``max_frame_bytes`` in its HELLO, so ``send`` refuses (FrameTooLargeError) what the peer would refuse.

Receiving: an asyncio.BufferedProtocol reads straight into the connection's stream buffer; frames under 16 KiB are
copied out of it (cheaper than any bookkeeping), larger ones are read straight into a buffer of their own from a
per-connection pool, so an image is copied once (kernel to that buffer) and ``receive`` returns a view of it. A pool
buffer is reused only once no view of it is alive any more (a caller's, or an event loop still sending it back), so
even views kept past the next ``receive`` stay intact. Complete frames queue in the connection; reading pauses while
more than 8 MiB are queued unread.

Sending: a small frame is joined with its header into one bytes object and written at once; a small frame sent
within 20 us of the previous write starts a burst, whose frames go out in one write at the end of the loop iteration
(one syscall for many frames; a lone request still leaves at once). Larger frames go out as header + parts without
joining (``writelines``: one sendmsg on uvloop and Python >= 3.12). Where the event loop keeps a reference to a
mutable buffer instead of copying it (uvloop, Python >= 3.12), ``send`` returns only once the socket took those bytes,
so callers may reuse their buffers as soon as ``send`` returns, as with every transport. ``send`` waits while more
than 1 MiB is unsent (pause_writing/resume_writing), so memory stays bounded.

Polling: when this end sent a frame since it last received one (it may be waiting for an answer), ``receive`` reads
the socket itself (``os.readv`` into the same buffers the loop's reader would use) for up to ``spin_ns`` before it
sleeps in the event loop, yielding the CPU between reads, under the spin credit of ``ShmTransport``: a miss costs
credit, and a connection without credit sleeps at once until a wait shows a spin would have caught the frame. A
receiver that only listens never polls (reading each frame as it lands cost a stream 40 % of its small-frame
rate). A frame sent after a ``receive`` that waited is a reply and goes out at once, never into a burst: a reply
corked to the end of the loop iteration cost the echo ~30 us per round trip.

Why the poll: each wake-up of a halted core costs 10-25 us on the project's 2-core machines, more than the rest of a
small round trip; reading the socket itself (not turning the event loop, which also takes the CPU a peer on the
same core needs) keeps the receiving core awake just long enough. Figures: docs/performance.md.

Limits, for peers that are not trusted (docs/security.md), kept by the listener (``_tcp_listener``): it holds at
most ``max_connections`` connections and ``max_handshakes`` unfinished handshakes (a new one evicts the oldest once
that waited 1 s, else it is reset and ``connect`` retries), each of which must finish within
``handshake_timeout_s``. The stream buffer is anonymous memory, resident only where data has landed, so an idle
connection costs a few KiB; refusals are counted in ``rejected`` and logged at most once a second.

Outside the loop: ``try_send`` writes a small frame at once when nothing waits before it, and ``receive_blocking``
reads the socket in the caller's thread (the poll's reads, then ``poll(2)``), for a caller in the loop's thread while
the loop is not running (the supervisor between calls). Whatever they cannot do they leave to ``send`` and
``receive``, having taken nothing.

Reconnection: a connection that breaks stays broken (TransportBrokenError on every later call). Whoever owns it (the
bus) closes it and calls ``connect`` again, which retries with exponential backoff (``uniros_async.backoff``, 5 ms
doubling to 500 ms) until ``connect_timeout_s``; frames that were in flight when the connection broke are lost, as
on any TCP link. There is deliberately no reconnecting wrapper here: only the owner knows what to resubscribe and
re-send. Every connection has TCP keepalive (``KEEPALIVE_IDLE_S``), so an end that only receives still learns within
seconds that its peer's socket is gone.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import mmap
import os
import select
import socket
import ssl
import struct
import sys
import time
from collections.abc import Callable, Sequence
from typing import cast

from uniros_async._log_throttle import LogThrottle
from uniros_async.backoff import Backoff
from uniros_async.errors import (
    AuthenticationError,
    ConfigError,
    FrameTooLargeError,
    TransportBrokenError,
    TransportClosedError,
)
from uniros_async.transports import base as _base
from uniros_async.transports._tcp_handshake import (
    FLAG_AUTH,
    HELLO,
    MAGIC,
    PROOF_BYTES,
    PROTOCOL_VERSION,
    TcpHandshake,
)
from uniros_async.transports._tcp_listener import TcpListener, format_uri, open_listener, parse_host_port
from uniros_async.transports.base import Buffer, Delivery, Transport, TransportOptions
from uniros_async.transports.exposure import is_loopback

__all__ = [
    "FLAG_AUTH",
    "HELLO",
    "MAGIC",
    "PROOF_BYTES",
    "PROTOCOL_VERSION",
    "TcpListener",
    "TcpTransport",
    "connect",
    "is_loopback",
    "listen",
    "open_connection",
    "open_listener",
]

logger = logging.getLogger(__name__)

_HEADER = struct.Struct("<I")
_pack_header = _HEADER.pack
_unpack_header = _HEADER.unpack_from
_WIRE_MAX_FRAME = 2**32 - 1  # what a u32 length prefix can announce

_STREAM_BYTES = 256 * 1024  # receive buffer of each connection: anonymous memory, only touched pages are resident
_READ_BYTES = 64 * 1024  # at most this much per read into the stream buffer (bounds the copy of a large frame's start)
_SMALL_FRAME_BYTES = 16 * 1024  # smaller frames are copied out of the stream buffer; larger get their own buffer
_JOIN_MAX_BYTES = 16 * 1024  # smaller frames are sent as one joined bytes object
_CORK_MAX_BYTES = 64 * 1024  # coalesced small frames are written once they reach this size
_BURST_S = 20e-6  # a small frame sent this soon after the previous write starts a coalesced burst
_POOL_BUFFERS = 16  # large-frame buffers kept for reuse per connection (at most _POOL_BYTES in all)
_POOL_BYTES = 16 * 1024 * 1024
_RX_HIGH_BYTES = 8 * 1024 * 1024  # pause reading while more than this is queued unread
_RX_LOW_BYTES = 2 * 1024 * 1024  # resume below this
_TX_HIGH_BYTES = 1024 * 1024  # send() waits while the event loop holds more than this unsent
_TX_LOW_BYTES = 256 * 1024
KEEPALIVE_IDLE_S = 2
"""TCP keepalive: a connection idle this long is probed every ``KEEPALIVE_INTERVAL_S``, and broken after
``KEEPALIVE_PROBES`` unanswered probes. A side that only receives (a subscriber, the domain's end of a node's
registry connection) otherwise never learns that its peer's socket is gone (a reset that reached only the peer, a
peer host that restarted): the probe is answered with a reset, and the owner reconnects."""
KEEPALIVE_INTERVAL_S = 1
KEEPALIVE_PROBES = 3
_HANG_UP = getattr(select, "POLLRDHUP", 0x2000)  # poll(2): the peer closed its end (POLLHUP, POLLERR: always reported)


def set_keepalive(sock: socket.socket) -> None:
    """Turn on TCP keepalive with this module's timings (``KEEPALIVE_IDLE_S`` and after): a dead peer is noticed
    within about 5 s of silence."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    for opt, value in (
        ("TCP_KEEPIDLE", KEEPALIVE_IDLE_S),
        ("TCP_KEEPINTVL", KEEPALIVE_INTERVAL_S),
        ("TCP_KEEPCNT", KEEPALIVE_PROBES),
    ):
        if hasattr(socket, opt):  # Linux; elsewhere the system's defaults apply
            sock.setsockopt(socket.IPPROTO_TCP, getattr(socket, opt), value)


_CLOSE_TIMEOUT_S = 1.0  # aclose waits this long for unsent bytes to leave, then aborts

# Before sleeping in the event loop, receive() reads the socket itself for up to spin_ns, yielding the CPU between
# reads (ShmTransport's rule): in a request/reply exchange the answer usually comes sooner than a sleeping process
# wakes up, and while both ends keep reading neither core halts. After a large send the window grows by 1 ns per
# byte sent, up to _SPIN_EXTRA_NS (the answer to 64 KiB took ~70 us). A spin that finds nothing costs credit; without
# credit no spin is tried until a wait turns out to have been short enough that a spin would have caught it. So an
# idle receiver spins a few times, then sleeps; a slow peer (a 10 Hz arm's states) stops the spinning at once.
_now_ns = _base.spin_clock_ns  # module globals: a spin reads them every poll
_yield = _base.spin_yield
_SPIN_CREDIT = _base.SPIN_CREDIT
_WAKEUP_NS = _base.SPIN_WAKEUP_NS  # a wait this much longer than the window would have been caught by it
_SPIN_EXTRA_NS = _base.SPIN_EXTRA_NS  # at most this much longer after a large send: 1 ns per byte sent
_SHARED_CORE_NS = 50_000  # a poll that lasts this long (or half its window) looks where the peer runs (_peer_here)
_LOOK_EVERY_NS = 1_000_000  # ... at most this often: a look reads /proc (~20 us)
_this_cpu = _base.this_cpu

# Python 3.11's selector transport copies what it cannot send at once; uvloop and 3.12+ keep a reference instead
# (and only they send a list of buffers with one sendmsg; 3.11's writelines joins them first).
_SELECTOR_COPIES = sys.version_info < (3, 12)

_HANDSHAKE, _FRAMES, _DEAD = 0, 1, 2


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


def _as_bytes_view(part: Buffer) -> memoryview:
    view = memoryview(part)
    if view.ndim != 1 or view.itemsize != 1:
        view = view.cast("B")  # transports slice by bytes: a float64 or 2-D view must look like bytes
    return view


_client_log = LogThrottle(logger)


class TcpTransport(Transport, asyncio.BufferedProtocol):
    """One end of a TCP connection carrying length-prefixed frames.

    Made by ``connect`` or ``TcpListener.accept``; the asyncio protocol callbacks (``connection_made``,
    ``get_buffer``, ...) belong to the event loop, not to callers.
    """

    delivery = Delivery.RELIABLE
    scheme = "tcp"
    _encrypted = False  # TlsTransport: True (the socket carries ciphertext; receive never reads it itself)
    spin_ns: int = 50_000
    """When ``receive`` may be waiting for an answer (this end sent a frame since it last received one), it reads
    the socket itself for up to this long before it sleeps in the event loop, yielding the CPU between reads, while
    spins keep finding frames (see ``_SPIN_CREDIT``). A receiver that only listens (a subscriber, the far end of a
    stream) never polls: it sleeps and reads what piled up in one go. Set it on the class or on one transport; 0
    always sleeps (a real-time worker's connections do: a SCHED_RR process that polls keeps lower-ranked ones from
    their cores)."""

    peer_pid: int | None = None
    """The peer's process id when it runs on this host (a worker sets its agent's): a poll that lasts half its
    window looks whether the peer runs on this core, and if so calls ``on_shared_core`` (``_peer_here``)."""
    on_shared_core: Callable[[int], None] | None = None
    """With ``peer_pid``: called with this core when the peer was found on it, to move this end elsewhere (a worker
    moves itself, ``runtime.worker``), as ``ShmTransport.on_shared_core``."""

    def __init__(self, options: TransportOptions, *, listener: TcpListener | None = None, uri: str = "") -> None:
        Transport.__init__(self)
        self._options = options
        self._key = bytes(options.auth_key) if options.auth_key is not None else None
        self._listener = listener
        self._loop = asyncio.get_running_loop()
        self._tr: asyncio.Transport | None = None
        self._peer = uri or "tcp://?"
        self._recv_limit = min(options.max_frame_bytes, _WIRE_MAX_FRAME)
        self._send_limit = self._recv_limit
        self._send_limit_is_peers = False
        # receive side
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
        self._next_look_ns = 0  # _peer_here: not before then
        self._sent_since_receive = 0  # bytes: only a receive that may be waiting for an answer polls, and longer
        # after a large send (the answer to 64 KiB took ~70 us here)
        # send side
        self._write_paused = False
        self._drain_waiters: collections.deque[asyncio.Future[None]] = collections.deque()
        self._cork: list[bytes] | None = None  # small frames to write at the end of this loop iteration
        self._cork_bytes = 0
        self._last_write_s = 0.0
        self._copies_on_write = False  # the event loop copies what it cannot send at once
        self._vectored = False  # writelines sends without joining
        self._stdlib = False
        # life cycle
        self._state = _HANDSHAKE
        self._ok = False  # handshake done, not closed, not broken: the fast paths' single check
        self._closed = False  # our own aclose
        self._error: tuple[str, BaseException | None] | None = None  # why the connection ended (message, cause)
        self._lost: asyncio.Future[None] = self._loop.create_future()
        self._ready: asyncio.Future[None] = self._loop.create_future()  # handshake done (client side)
        self._ready.add_done_callback(_consume_exception)
        self._hs = TcpHandshake(
            key=self._key, listener=listener is not None, max_frame_bytes=self._recv_limit, peer=self._peer
        )
        self._hs_timer: asyncio.TimerHandle | None = None
        self._hs_started_s = 0.0
        self._hs_dropped = False  # the peer hung up (or reset) during the handshake: a full listener does that
        self._counted = listener is not None  # in the listener's open connections until connection_lost
        self._unmade_timer: asyncio.TimerHandle | None = None
        if listener is not None and self._encrypted:
            # Under TLS the event loop makes this protocol before the TLS handshake and never tells it when that
            # handshake fails (no connection_made, no connection_lost); the handshake is bounded by
            # handshake_timeout_s, so a connection not made a second after that never will be: stop counting it.
            self._unmade_timer = self._loop.call_later(options.handshake_timeout_s + 1.0, self._uncount)

    # ------------------------------------------------------------------------------------------ public API

    @property
    def max_frame_bytes(self) -> int:
        return self._send_limit

    @property
    def peer(self) -> str:
        return self._peer

    @property
    def sockname(self) -> tuple[str, int]:
        """Our own (host, port) of this connection."""
        assert self._tr is not None
        name = self._tr.get_extra_info("sockname")
        return name[0], name[1]

    def has_news(self) -> bool:
        """Whether ``receive`` would return at once: a frame is buffered, or the connection has ended."""
        return self._error is not None or bool(self._frames)

    def fileno(self) -> int:
        """The connection's socket descriptor (-1 before connecting, once closed, or under TLS, where readable
        ciphertext says nothing about whole frames): a caller outside the event loop can ``select`` on it to learn,
        without reading, whether the peer sent data the loop has not taken."""
        if self._encrypted:
            return -1
        sock = self._tr.get_extra_info("socket") if self._tr is not None else None
        return sock.fileno() if sock is not None else -1

    async def send(self, frame: Buffer | Sequence[Buffer]) -> None:
        """Send one frame. If cancelled while waiting for the peer to catch up, nothing was sent; once the frame
        was handed to the event loop it goes out whole (the connection never carries half a frame). Returns
        once the event loop holds no reference to a mutable buffer of ``frame``: the caller may reuse it.

        Raises:
            TransportClosedError: our own code closed this end.
            TransportBrokenError: the peer or the network failed; ``__cause__`` holds the OSError.
            FrameTooLargeError: over our or the peer's ``max_frame_bytes``; nothing was sent.
        """
        kind = type(frame)
        parts: list[memoryview] | None = None
        if kind is bytes or kind is bytearray:
            one = cast(bytes, frame)
            n = len(one)
        elif kind is list or kind is tuple:
            parts = [_as_bytes_view(p) for p in cast(Sequence[Buffer], frame)]
            n = sum(p.nbytes for p in parts)
        else:  # a memoryview, or any other contiguous buffer (numpy array, array.array)
            one = memoryview(cast(Buffer, frame))  # type: ignore[assignment]
            n = one.nbytes  # type: ignore[attr-defined]
        if not self._ok:
            self._raise_unusable("send")
        if n > self._send_limit:
            whose = "the peer's" if self._send_limit_is_peers else "our"
            raise FrameTooLargeError(
                f"frame of {n} bytes exceeds {whose} max_frame_bytes={self._send_limit} on {self._peer}"
            )
        if self._write_paused:
            await self._wait_writable()
        tr = self._tr
        assert tr is not None
        if n <= _JOIN_MAX_BYTES:
            # One bytes object per frame: a copy of at most 16 KiB costs less than a second syscall.
            data = _pack_header(n) + one if parts is None else b"".join((_pack_header(n), *parts))
            cork = self._cork
            if cork is not None:
                cork.append(data)
                self._cork_bytes += len(data)
                if self._cork_bytes >= _CORK_MAX_BYTES:
                    self._flush_cork()
            else:
                now = time.perf_counter()
                if now - self._last_write_s > _BURST_S:
                    tr.write(data)  # a lone frame (a request, a periodic message): out at once
                else:
                    # A burst: this and the following small frames go out in one write at the end of this loop
                    # iteration (one syscall for many frames instead of one each).
                    self._cork = [data]
                    self._cork_bytes = len(data)
                    self._loop.call_soon(self._uncork)
                self._last_write_s = now
        else:
            self._flush_cork()
            if parts is None:
                parts = [_as_bytes_view(one)]
            if self._vectored:
                tr.writelines([_pack_header(n), *parts])
                if self._stdlib:
                    # CPython 3.12/3.13's selector writelines() skips its flow-control check; this call runs it.
                    tr.set_write_buffer_limits(high=_TX_HIGH_BYTES, low=_TX_LOW_BYTES)
            else:
                tr.write(_pack_header(n))
                for p in parts:
                    tr.write(p)
            if (
                not self._copies_on_write
                and tr.get_write_buffer_size()
                and not all(isinstance(p.obj, bytes) for p in parts)
            ):
                await self._wait_flushed()
        self._count_sent(n)

    def _count_sent(self, n: int) -> None:
        self._sent_since_receive += n  # the next receive may be waiting for an answer: it polls
        stats = self.stats
        stats.frames_sent += 1
        stats.bytes_sent += n

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

    def try_send(self, frame: bytes) -> bool:
        """Send a small ``frame`` at once, outside the event loop, when nothing waits before it (no burst corked,
        nothing unsent, writing not paused); True if the socket took it whole. False: nothing was sent, ``send``
        must do it (it waits, or raises what is wrong). The counterpart of ``ShmTransport.try_send``, for a caller
        in the loop's own thread while the loop is not running (the supervisor between calls)."""
        n = len(frame)
        tr = self._tr
        if (
            tr is None
            or not self._ok
            or self._closed
            or self._write_paused
            or self._cork is not None
            or n > _JOIN_MAX_BYTES
            or n > self._send_limit
            or tr.get_write_buffer_size()
        ):
            return False
        tr.write(_pack_header(n) + frame)  # the loop's transport writes it to the socket now: its buffer is empty
        self._last_write_s = time.perf_counter()
        self._count_sent(n)
        return True

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
        window_ns = self.spin_ns + min(self._sent_since_receive, _SPIN_EXTRA_NS)
        if self._spin_credit > 0:
            self._spin(window_ns)
        return window_ns

    def _waited(self, t0: int, window_ns: int) -> None:
        """After a wait that began at ``t0``: without credit, a wait a poll would have caught earns one back."""
        if window_ns and self._spin_credit <= 0 and _now_ns() - t0 < window_ns + _WAKEUP_NS:
            self._spin_credit = 1  # a spin would have caught this one: try spinning again

    async def aclose(self) -> None:
        """Close this end; idempotent. Frames already sent are flushed for up to 1 s, then the socket is
        aborted. Tasks blocked in ``receive`` or ``send`` get TransportClosedError."""
        if self._closed:
            return
        self._closed = True
        self._ok = False
        self._wake_all()
        tr = self._tr
        if tr is None or self._lost.done():
            return
        if self._state == _FRAMES and self._error is None:
            self._flush_cork()
        tr.close()
        try:
            async with asyncio.timeout(_CLOSE_TIMEOUT_S):
                await asyncio.shield(self._lost)
        except TimeoutError:
            tr.abort()
        except asyncio.CancelledError:
            tr.abort()
            raise

    # ------------------------------------------------------------------------------------------ asyncio protocol

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        tr = cast(asyncio.Transport, transport)  # uvloop's transports do not subclass asyncio's
        self._tr = tr
        if self._unmade_timer is not None:
            self._unmade_timer.cancel()
            self._unmade_timer = None
        sock = tr.get_extra_info("socket")
        if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            set_keepalive(sock)
        if sock is not None and hasattr(os, "readv") and not self._encrypted:
            self._fd = sock.fileno()  # under TLS the socket carries ciphertext: only the event loop reads it
        peer = tr.get_extra_info("peername")
        if peer:
            self._peer = format_uri(peer[0], peer[1], self.scheme)
        tr.set_write_buffer_limits(high=_TX_HIGH_BYTES, low=_TX_LOW_BYTES)
        self._stdlib = type(tr).__module__ == "asyncio.selector_events"
        self._copies_on_write = self._stdlib and _SELECTOR_COPIES
        self._vectored = not self._copies_on_write
        self._hs.peer = self._peer
        if self._listener is not None:
            if not self._listener._handshake_started(self):
                self._state = _DEAD
                self._set_error(f"{self._peer} refused: too many unfinished handshakes")
                tr.abort()  # before our HELLO: the peer sees a reset, not a finished handshake, and retries
                return
            self._hs_started_s = self._loop.time()
            self._hs_timer = self._loop.call_later(self._options.handshake_timeout_s, self._handshake_expired)
        tr.write(self._hs.hello())

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

    def eof_received(self) -> bool:
        if self._state == _HANDSHAKE:
            self._hs_dropped = self._retryable_drop()
            self._handshake_failed(TransportBrokenError(f"{self._peer} closed the connection during the handshake"))
        elif self._error is None:
            if self._big is not None or self._rend > self._rpos:
                got = self._big_got if self._big is not None else self._rend - self._rpos
                self._set_error(
                    f"peer closed the connection in the middle of a frame ({got} bytes of it arrived): {self._peer}"
                )
            else:
                self._set_error(f"peer closed the connection: {self._peer}")
        return False  # let asyncio close our end too

    def connection_lost(self, exc: Exception | None) -> None:
        self._fd = -1  # the event loop closes the socket; its number may soon name another file
        self._uncount()
        if self._state == _HANDSHAKE:
            self._hs_dropped = (exc is None or isinstance(exc, ConnectionError)) and self._retryable_drop()
            self._handshake_failed(
                TransportBrokenError(f"connection to {self._peer} lost during the handshake: {exc or 'closed'}"),
                cause=exc,
            )
        if self._error is None:
            if exc is None:
                self._set_error(f"peer closed the connection: {self._peer}")
            elif self._big is not None or self._rend > self._rpos:
                self._set_error(f"connection to {self._peer} lost in the middle of a frame: {exc}", exc)
            else:
                self._set_error(f"connection to {self._peer} lost: {exc}", exc)
        elif exc is not None and self._error[1] is None:
            self._error = (self._error[0], exc)
        if self._hs_timer is not None:
            self._hs_timer.cancel()
        self._cork = None
        self._wake_all()
        if not self._lost.done():
            self._lost.set_result(None)

    def pause_writing(self) -> None:
        self._write_paused = True

    def resume_writing(self) -> None:
        self._write_paused = False
        self._wake_drain_waiters()

    # ------------------------------------------------------------------------------------------ receiving

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
        ``peer_pid``, a spin that lasted half its window (at most ``_SHARED_CORE_NS``) looks once where the peer runs
        (``_peer_here``)."""
        fd = self._fd
        if fd < 0 or not self._ok:
            return
        frames = self._frames
        now = _now_ns()
        deadline = now + window_ns
        look_at = now + min(_SHARED_CORE_NS, window_ns // 2) if self.peer_pid else deadline
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
        moved elsewhere (``on_shared_core``). At most once per ``_LOOK_EVERY_NS``.

        A poll only pays while the peer runs on another core. A socket wakes its reader with a sync wake-up, which
        places a worker woken by its agent on the agent's core; the two then take turns on it (the worker's poll
        holds the core the agent needs for its next request, the worker's wake-up preempts the agent) while the
        other core does other work: a CartPole step over tcp on loopback took ~120-130 us so against ~30 us on two
        cores, for the life of the pair (docs/performance.md). ``ShmTransport`` learns where its peer runs from
        their shared page; tcp has none, so this end reads the peer's last core from /proc (~20 us).
        """
        now = _now_ns()
        if now < self._next_look_ns or self.on_shared_core is None:
            return
        self._next_look_ns = now + _LOOK_EVERY_NS
        cpu = _this_cpu()
        try:
            with open(f"/proc/{self.peer_pid}/stat", "rb") as f:
                peer_cpu = int(f.read().rpartition(b")")[2].split()[36])
        except (OSError, ValueError, IndexError):  # gone, or no /proc here: look no more
            self.peer_pid = None
            return
        if cpu >= 0 and peer_cpu == cpu:
            self.on_shared_core(cpu)

    def _retryable_drop(self) -> bool:
        """Whether a hang-up during the handshake may be a full listener (worth a retry). Under TLS a listener
        that refuses our certificate hangs up too, before its HELLO: only a drop after the HELLO (an eviction)
        counts there."""
        return not self._encrypted or self._hs.peer_max_frame_bytes is not None

    def _uncount(self) -> None:
        """Leave the listener's count of open connections (once)."""
        if self._counted and self._listener is not None:
            self._counted = False
            self._listener._open -= 1
        self._unmade_timer = None

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

    # ------------------------------------------------------------------------------------------ handshake

    def _handshake_data(self) -> None:
        pos = self._rpos
        try:
            used, reply = self._hs.feed(self._rview[pos : self._rend])
        except (TransportBrokenError, AuthenticationError) as exc:
            self._handshake_failed(exc)
            return
        self._rpos = pos + used
        if reply and self._tr is not None:
            self._tr.write(reply)
        if self._hs.done:
            peer_max = self._hs.peer_max_frame_bytes
            if peer_max is not None and peer_max < self._send_limit:
                self._send_limit = peer_max
                self._send_limit_is_peers = True
            self._handshake_done()

    def _handshake_done(self) -> None:
        self._state = _FRAMES
        self._ok = True
        if self._hs_timer is not None:
            self._hs_timer.cancel()
            self._hs_timer = None
        if self._listener is not None:
            self._listener._handshake_succeeded(self)
        elif not self._ready.done():
            self._ready.set_result(None)
        if self._rend > self._rpos:
            self._parse_frames()  # the peer may already have sent frames behind its handshake

    def _handshake_failed(self, exc: Exception, cause: BaseException | None = None) -> None:
        if self._state != _HANDSHAKE:
            return
        self._state = _DEAD
        self._set_error(str(exc), cause)
        if self._hs_timer is not None:
            self._hs_timer.cancel()
            self._hs_timer = None
        if self._listener is not None:
            self._listener._handshake_rejected(self, str(exc))
            self.stats.rejected += 1
        elif not self._ready.done():
            if cause is not None:
                exc.__cause__ = cause
            self._ready.set_exception(exc)
        if self._tr is not None:
            self._tr.close()  # not abort: a peer refused for its version or key should still read our hello

    def _handshake_expired(self) -> None:
        self._hs_timer = None
        timeout_s = self._options.handshake_timeout_s
        msg = f"{self._peer} did not complete the handshake within {timeout_s} s"
        self._handshake_failed(TransportBrokenError(msg))

    # ------------------------------------------------------------------------------------------ helpers

    def _set_error(self, msg: str, cause: BaseException | None = None) -> None:
        self._error = (msg, cause)
        self._ok = False
        self._wake_all()

    def _raise_unusable(self, op: str) -> None:
        if self._closed:
            raise TransportClosedError(f"{op} on closed transport to {self._peer}")
        if self._error is not None:
            msg, cause = self._error
            raise TransportBrokenError(msg) from cause
        raise TransportBrokenError(f"{op} on {self._peer} before the handshake completed")

    def _wake_all(self) -> None:
        w = self._rx_waiter
        if w is not None and not w.done():
            w.set_result(None)
        self._wake_drain_waiters()

    def _wake_drain_waiters(self) -> None:
        waiters = self._drain_waiters
        while waiters:
            w = waiters.popleft()
            if not w.done():
                w.set_result(None)

    async def _wait_writable(self) -> None:
        while self._write_paused and self._ok:
            fut = self._loop.create_future()
            self._drain_waiters.append(fut)
            await fut  # cancelled: nothing of this frame was written
        if not self._ok:
            self._raise_unusable("send")

    async def _wait_flushed(self) -> None:
        """Wait until the event loop no longer holds bytes of the frame just written (it kept a reference to the
        caller's mutable buffer instead of a copy). A write limit of 0 makes the loop call resume_writing exactly
        when its buffer is empty."""
        tr = self._tr
        assert tr is not None
        tr.set_write_buffer_limits(high=0, low=0)
        try:
            while self._write_paused and self._ok:
                fut = self._loop.create_future()
                self._drain_waiters.append(fut)
                await fut
        finally:
            if not tr.is_closing():
                tr.set_write_buffer_limits(high=_TX_HIGH_BYTES, low=_TX_LOW_BYTES)
        if self._error is not None and not self._closed:
            self._raise_unusable("send")

    def _uncork(self) -> None:
        self._flush_cork()
        self._cork = None
        self._last_write_s = time.perf_counter()

    def _flush_cork(self) -> None:
        cork = self._cork
        if cork:
            data = cork[0] if len(cork) == 1 else b"".join(cork)
            cork.clear()
            self._cork_bytes = 0
            if self._tr is not None and self._error is None:
                self._tr.write(data)


def _consume_exception(fut: asyncio.Future[None]) -> None:
    # The handshake result may fail after connect() stopped waiting (timeout); do not log "never retrieved".
    if not fut.cancelled():
        fut.exception()


async def listen(uri: str, options: TransportOptions) -> TcpListener:
    """Listen at ``tcp://HOST:PORT``; port 0 picks a free port and ``uri`` of the result reports it.

    HOST is the interface bound; without one (``tcp://:0``), ``options.bind_host`` (loopback by default). A
    non-loopback HOST needs ``options.auth_key`` (or ``options.insecure``). The listener's caps are
    ``options.max_connections``, ``max_handshakes`` and ``handshake_timeout_s`` (see ``TcpListener``).

    Raises:
        ConfigError: the URI is malformed, or a non-loopback HOST without auth_key and without insecure.
        OSError: the address cannot be bound (in use, no such interface).
    """
    return await open_listener(uri, options, TcpTransport)


async def connect(uri: str, options: TransportOptions) -> TcpTransport:
    """Connect to a listener at ``tcp://HOST:PORT`` and complete the handshake.

    Refused connections (a listener still starting), and connections the listener drops during the handshake (it
    is at ``max_connections``, or evicted us among more than ``max_handshakes`` at once), are retried with backoff
    from 5 ms doubling to 500 ms, until ``options.connect_timeout_s`` has passed since the call, handshake included.
    Cancelling leaves nothing open.

    Raises:
        ConfigError: the URI has no host or port.
        TimeoutError: nobody accepted and completed the handshake within ``connect_timeout_s`` (names the URI).
        AuthenticationError: the key settings differ or the listener failed to prove the shared key.
        TransportBrokenError: the peer is not a uniros listener (or speaks another version).
    """
    return await open_connection(uri, options, TcpTransport)


async def open_connection(
    uri: str, options: TransportOptions, cls: type[TcpTransport], ssl_context: ssl.SSLContext | None = None
) -> TcpTransport:
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
