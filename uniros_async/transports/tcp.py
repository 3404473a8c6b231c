"""Network transport: length-prefixed frames over TCP, ``tcp://HOST:PORT``.

Wire format (little-endian)::

    hello   client -> listener   HELLO = MAGIC(8s) version(u16) flags(u16) max_frame_bytes(u64) nonce(32s)
            listener -> client   HELLO, then proof(32s) if flags has FLAG_AUTH
            client -> listener   proof(32s)                                     (only with FLAG_AUTH)
    frame   either way           length(u32) payload(length bytes)

With a shared ``auth_key`` each side proves knowledge of it without sending it: the listener sends
HMAC-SHA256(key, b"uniros-tcp listener" + client_nonce + listener_nonce), the client answers with the same over
b"uniros-tcp client"; both are checked with hmac.compare_digest. Fresh random nonces on both sides defeat replay,
and the two labels defeat reflection. Both ends refuse a peer whose key setting differs from their own. Each side
announces its ``max_frame_bytes``, so ``send`` refuses (FrameTooLargeError) what the peer would refuse.

Receiving: an asyncio.BufferedProtocol reads straight into a preallocated stream buffer; frames under 16 KiB are
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

Measured on the project's 2-core VM (echo server in another process, quiet machine, ``uniros bench transport``,
docs/perf/history.md): 277 B round trip p50 20-24 us with the default 50 us poll, against 62-99 us without it and
79-108 us for pyzmq tcp; 64 KiB 66-75 us (pyzmq 114-163 us). Raw Python sockets in the same hour: 28 us blocking,
12 us busy-polling; each wake-up of a halted core costs 10-25 us here, which is what the poll saves. An earlier
poll that turned the event loop (``asyncio.sleep(0)``) instead of reading the socket reached 26-30 us on uvloop
only and took the CPU its peer needed under load, so it was opt-in. 640x480x3 images one way: 4,150-4,950/s
(pyzmq PUSH/PULL 2,900-3,300/s).

Outside the loop: ``try_send`` writes a small frame at once when nothing waits before it, and ``receive_blocking``
reads the socket in the caller's thread (the poll's reads, then ``poll(2)``), for a caller in the loop's thread while
the loop is not running (the supervisor between calls). Whatever they cannot do they leave to ``send`` and
``receive``, having taken nothing.

Reconnection: a connection that breaks stays broken (TransportBrokenError on every later call). Whoever owns it
(the bus) closes it and calls ``connect`` again, which retries with exponential backoff (5 ms doubling to 500 ms)
until ``connect_timeout_s``; frames that were in flight when the connection broke are lost, as on any TCP link.
There is deliberately no reconnecting wrapper here: only the owner knows what to resubscribe and re-send. Every
connection has TCP keepalive (``KEEPALIVE_IDLE_S``), so an end that only receives still learns within seconds that
its peer's socket is gone.
"""

from __future__ import annotations

import asyncio
import collections
import hashlib
import hmac
import logging
import os
import select
import socket
import struct
import sys
import time
from collections.abc import Sequence
from typing import cast
from urllib.parse import urlsplit

from uniros_async.errors import (
    AuthenticationError,
    ConfigError,
    FrameTooLargeError,
    TransportBrokenError,
    TransportClosedError,
)
from uniros_async.transports import base as _base
from uniros_async.transports.base import Buffer, Delivery, Listener, Transport, TransportOptions, split_uri

__all__ = [
    "FLAG_AUTH",
    "HELLO",
    "MAGIC",
    "PROOF_BYTES",
    "PROTOCOL_VERSION",
    "TcpListener",
    "TcpTransport",
    "connect",
    "listen",
]

logger = logging.getLogger(__name__)

MAGIC = b"\x89UNIROS\n"
"""First bytes of every uniros tcp connection (high bit and newline catch 7-bit and text-mode mangling)."""
PROTOCOL_VERSION = 1
FLAG_AUTH = 1
HELLO = struct.Struct("<8sHHQ32s")
"""magic, version, flags, max_frame_bytes, nonce."""
PROOF_BYTES = 32
_LISTENER_LABEL = b"uniros-tcp listener"
_CLIENT_LABEL = b"uniros-tcp client"

_HEADER = struct.Struct("<I")
_pack_header = _HEADER.pack
_unpack_header = _HEADER.unpack_from
_WIRE_MAX_FRAME = 2**32 - 1  # what a u32 length prefix can announce

_STREAM_BYTES = 256 * 1024  # preallocated receive buffer of each connection
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
_BACKOFF_FIRST_S = 0.005
_BACKOFF_MAX_S = 0.5
KEEPALIVE_IDLE_S = 2
"""TCP keepalive: a connection idle this long is probed every ``KEEPALIVE_INTERVAL_S``, and broken after
``KEEPALIVE_PROBES`` unanswered probes. A side that only receives (a subscriber, the domain's end of a node's
registry connection) otherwise never learns that its peer's socket is gone (a reset that reached only the peer, a
peer host that restarted): the probe is answered with a reset, and the owner reconnects."""
KEEPALIVE_INTERVAL_S = 1
KEEPALIVE_PROBES = 3


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

# Python 3.11's selector transport copies what it cannot send at once; uvloop and 3.12+ keep a reference instead
# (and only they send a list of buffers with one sendmsg; 3.11's writelines joins them first).
_SELECTOR_COPIES = sys.version_info < (3, 12)

_HANDSHAKE, _FRAMES, _DEAD = 0, 1, 2


def _proof(key: bytes, label: bytes, client_nonce: bytes, listener_nonce: bytes) -> bytes:
    return hmac.new(key, label + client_nonce + listener_nonce, hashlib.sha256).digest()


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


class _LogThrottle:
    """At most one warning per second per listener; the next one says how many were not logged."""

    def __init__(self) -> None:
        self._next_s = 0.0
        self._suppressed = 0

    def warning(self, msg: str, *args: object) -> None:
        now = time.monotonic()
        if now < self._next_s:
            self._suppressed += 1
            return
        self._next_s = now + 1.0
        if self._suppressed:
            msg += " (%d similar messages suppressed)"
            args = (*args, self._suppressed)
            self._suppressed = 0
        logger.warning(msg, *args)


_client_log = _LogThrottle()


class TcpTransport(Transport, asyncio.BufferedProtocol):
    """One end of a TCP connection carrying length-prefixed frames.

    Made by ``connect`` or ``TcpListener.accept``; the asyncio protocol callbacks (``connection_made``,
    ``get_buffer``, ...) belong to the event loop, not to callers.
    """

    delivery = Delivery.RELIABLE
    scheme = "tcp"
    spin_ns: int = 50_000
    """When ``receive`` may be waiting for an answer (this end sent a frame since it last received one), it reads
    the socket itself for up to this long before it sleeps in the event loop, yielding the CPU between reads, while
    spins keep finding frames (see ``_SPIN_CREDIT``). A receiver that only listens (a subscriber, the far end of a
    stream) never polls: it sleeps and reads what piled up in one go. Set it on the class or on one transport; 0
    always sleeps (a real-time worker's connections do: a SCHED_RR process that polls keeps lower-ranked ones from
    their cores)."""

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
        self._rbuf = bytearray(_STREAM_BYTES)
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
        self._hs_step = 0
        self._hs_timer: asyncio.TimerHandle | None = None
        self._nonce = os.urandom(32)
        self._peer_nonce = b""

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
        """The connection's socket descriptor (-1 before connecting or once closed): a caller outside the event
        loop can ``select`` on it to learn, without reading, whether the peer sent data the loop has not taken."""
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

    def receive_blocking(self, timeout_s: float) -> memoryview | None:
        """``receive`` in the calling thread while the event loop does not run (the agent's thread waiting for its
        workers' replies): a frame already queued, or one read from the socket here (``_spin``'s reads, then
        ``poll(2)`` on the socket for at most ``timeout_s``). Returns None when it cannot be had this way: nothing
        came in time, something is unsent (only the loop sends it), reading is paused, the peer hung up or broke
        the protocol, or this end is closed. Nothing was consumed then: ``receive`` must be awaited (it delivers
        the frame or raises what is wrong)."""
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
                if not poller.poll(-(-left_ns // 1_000_000)):
                    continue
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
        sock = tr.get_extra_info("socket")
        if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            set_keepalive(sock)
        if sock is not None and hasattr(os, "readv"):
            self._fd = sock.fileno()
        peer = tr.get_extra_info("peername")
        if peer:
            self._peer = _format_uri(peer[0], peer[1])
        tr.set_write_buffer_limits(high=_TX_HIGH_BYTES, low=_TX_LOW_BYTES)
        self._stdlib = type(tr).__module__ == "asyncio.selector_events"
        self._copies_on_write = self._stdlib and _SELECTOR_COPIES
        self._vectored = not self._copies_on_write
        flags = FLAG_AUTH if self._key is not None else 0
        tr.write(HELLO.pack(MAGIC, PROTOCOL_VERSION, flags, self._recv_limit, self._nonce))
        if self._listener is not None:
            self._listener._handshaking.add(self)
            self._hs_timer = self._loop.call_later(self._options.connect_timeout_s, self._handshake_expired)

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
        if self._state == _HANDSHAKE:
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
        stream, an error, paused reading) is left to the event loop, which meets it on its next read."""
        fd = self._fd
        if fd < 0 or not self._ok:
            return
        frames = self._frames
        deadline = _now_ns() + window_ns
        readv = os.readv
        while not self._reading_paused:
            try:
                n = readv(fd, (self.get_buffer(-1),))
            except (BlockingIOError, InterruptedError):
                if _now_ns() > deadline:
                    self._spin_credit -= 1
                    return
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
        view = self._rview
        while True:
            pos, avail = self._rpos, self._rend - self._rpos
            if self._hs_step == 0:
                check = min(avail, len(MAGIC))
                if view[pos : pos + check] != MAGIC[:check]:
                    head = bytes(view[pos : pos + min(avail, 16)])
                    self._handshake_failed(
                        TransportBrokenError(f"{self._peer} is not a uniros tcp peer: it sent {head!r}")
                    )
                    return
                if avail < HELLO.size:
                    return
                _, version, flags, max_frame, nonce = HELLO.unpack_from(self._rbuf, pos)
                self._rpos = pos + HELLO.size
                if not self._hello_received(version, flags, max_frame, nonce):
                    return
            elif self._hs_step == 1:
                if avail < PROOF_BYTES:
                    return
                proof = bytes(view[pos : pos + PROOF_BYTES])
                self._rpos = pos + PROOF_BYTES
                if not self._proof_received(proof):
                    return
            else:
                return

    def _hello_received(self, version: int, flags: int, max_frame: int, nonce: bytes) -> bool:
        tr = self._tr
        assert tr is not None
        if version != PROTOCOL_VERSION:
            self._handshake_failed(
                TransportBrokenError(f"{self._peer} speaks uniros tcp version {version}, we speak {PROTOCOL_VERSION}")
            )
            return False
        if bool(flags & FLAG_AUTH) != (self._key is not None):
            if self._key is None:
                msg = f"{self._peer} requires an auth_key and we have none"
            else:
                msg = f"{self._peer} does not authenticate (no auth_key) but ours is set"
            self._handshake_failed(AuthenticationError(msg))
            return False
        if max_frame < self._send_limit:
            self._send_limit = max_frame
            self._send_limit_is_peers = True
        self._peer_nonce = nonce
        if self._listener is not None:
            if self._key is not None:
                tr.write(_proof(self._key, _LISTENER_LABEL, nonce, self._nonce))
                self._hs_step = 1
                return True
            self._handshake_done()
            return False
        if self._key is not None:
            self._hs_step = 1
            return True
        self._handshake_done()
        return False

    def _proof_received(self, proof: bytes) -> bool:
        assert self._key is not None and self._tr is not None
        if self._listener is not None:
            expected = _proof(self._key, _CLIENT_LABEL, self._peer_nonce, self._nonce)
            if not hmac.compare_digest(proof, expected):
                self._handshake_failed(AuthenticationError(f"{self._peer} failed to prove the shared auth_key"))
                return False
        else:
            expected = _proof(self._key, _LISTENER_LABEL, self._nonce, self._peer_nonce)
            if not hmac.compare_digest(proof, expected):
                self._handshake_failed(
                    AuthenticationError(f"listener {self._peer} failed to prove the shared auth_key (keys differ)")
                )
                return False
            self._tr.write(_proof(self._key, _CLIENT_LABEL, self._nonce, self._peer_nonce))
        self._handshake_done()
        return False

    def _handshake_done(self) -> None:
        self._state = _FRAMES
        self._ok = True
        self._hs_step = 2
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
        timeout_s = self._options.connect_timeout_s
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


class TcpListener(Listener):
    """Accepts TCP connections; each peer that passes the handshake is handed out by ``accept``."""

    def __init__(self, options: TransportOptions) -> None:
        self._options = options
        self._server: asyncio.Server | None = None
        self._uri = ""
        self._address: tuple[str, int] = ("", 0)
        self._ready: collections.deque[TcpTransport] = collections.deque()
        self._accept_waiter: asyncio.Future[None] | None = None
        self._handshaking: set[TcpTransport] = set()
        self._rejected = 0
        self._closed = False
        self._log = _LogThrottle()

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

    async def accept(self) -> TcpTransport:
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

    def _handshake_succeeded(self, t: TcpTransport) -> None:
        self._handshaking.discard(t)
        if self._closed:
            t._tr.close()  # type: ignore[union-attr]
            return
        self._ready.append(t)
        if self._accept_waiter is not None and not self._accept_waiter.done():
            self._accept_waiter.set_result(None)

    def _handshake_rejected(self, t: TcpTransport, reason: str) -> None:
        self._handshaking.discard(t)
        if not self._closed:
            self._count_rejection(t.peer, reason)

    def _count_rejection(self, peer: str, reason: str) -> None:
        self._rejected += 1
        self._log.warning("tcp listener %s rejected %s: %s", self._uri, peer, reason)


def _host_port(uri: str, default_host: str) -> tuple[str, int]:
    scheme, _ = split_uri(uri)
    if scheme != "tcp":
        raise ConfigError(f"expected a tcp:// URI, got {uri!r}")
    parts = urlsplit(uri)
    if parts.path not in ("", "/") or parts.query or parts.fragment:
        raise ConfigError(f"expected tcp://HOST:PORT, got {uri!r}")
    try:
        port = parts.port or 0
    except ValueError as exc:
        raise ConfigError(f"expected tcp://HOST:PORT with a port in 0..65535, got {uri!r}") from exc
    return parts.hostname or default_host, port


def _format_uri(host: str, port: int) -> str:
    return f"tcp://[{host}]:{port}" if ":" in host else f"tcp://{host}:{port}"


async def listen(uri: str, options: TransportOptions) -> TcpListener:
    """Listen at ``tcp://HOST:PORT``; port 0 picks a free port and ``uri`` of the result reports it.

    HOST is the interface bound; without one (``tcp://:0``), ``options.bind_host`` (loopback by default).
    A peer has ``options.connect_timeout_s`` to complete the handshake.

    Raises:
        ConfigError: the URI is malformed.
        OSError: the address cannot be bound (in use, no such interface).
    """
    host, port = _host_port(uri, options.bind_host)
    lst = TcpListener(options)
    loop = asyncio.get_running_loop()
    server = await loop.create_server(lambda: TcpTransport(options, listener=lst), host, port, reuse_address=True)
    lst._server = server
    sockname = server.sockets[0].getsockname()
    lst._address = (sockname[0], sockname[1])
    lst._uri = _format_uri(sockname[0], sockname[1])
    return lst


async def connect(uri: str, options: TransportOptions) -> TcpTransport:
    """Connect to a listener at ``tcp://HOST:PORT`` and complete the handshake.

    Refused connections (a listener still starting) are retried with backoff from 5 ms doubling to 500 ms, until
    ``options.connect_timeout_s`` has passed since the call, handshake included. Cancelling leaves nothing open.

    Raises:
        ConfigError: the URI has no host or port.
        TimeoutError: nobody accepted and completed the handshake within ``connect_timeout_s`` (names the URI).
        AuthenticationError: the key settings differ or the listener failed to prove the shared key.
        TransportBrokenError: the peer is not a uniros listener (or speaks another version).
    """
    host, port = _host_port(uri, "")
    if not host or not port:
        raise ConfigError(f"connect needs tcp://HOST:PORT with a nonzero port, got {uri!r}")
    loop = asyncio.get_running_loop()
    timeout_s = options.connect_timeout_s
    deadline = loop.time() + timeout_s
    delay = _BACKOFF_FIRST_S
    last: OSError | None = None
    while True:
        try:
            async with asyncio.timeout_at(deadline):
                _, t = await loop.create_connection(lambda: TcpTransport(options, uri=uri), host, port)
            break
        except TimeoutError:
            raise TimeoutError(f"could not connect to {uri} within {timeout_s} s (last error: {last})") from last
        except OSError as exc:  # refused while the listener starts, unreachable, ... : retry until the deadline
            last = exc
            remaining = deadline - loop.time()
            if remaining <= 0:
                raise TimeoutError(f"could not connect to {uri} within {timeout_s} s (last error: {exc})") from exc
            await asyncio.sleep(min(delay, remaining))
            delay = min(delay * 2, _BACKOFF_MAX_S)
    try:
        async with asyncio.timeout_at(deadline):
            await asyncio.shield(t._ready)
    except TimeoutError as exc:
        await t.aclose()
        raise TimeoutError(
            f"{uri} accepted the connection but did not complete the handshake within {timeout_s} s"
        ) from exc
    except BaseException:
        await t.aclose()
        raise
    return t
