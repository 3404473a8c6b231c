"""Network transport: length-prefixed frames over TCP, ``tcp://HOST:PORT``.

Wire format: after the handshake (``_tcp_handshake``: HELLO both ways, then with an ``auth_key`` an HMAC proof
both ways), each frame is ``length(u32, little-endian) payload(length bytes)``. Each side announces its
``max_frame_bytes`` in its HELLO, so ``send`` refuses (FrameTooLargeError) what the peer would refuse.

Receiving: ``_tcp_receive`` (the stream buffer, large frames in buffers of their own, and the poll of the socket
while an answer is due, under the rule of ``_spin`` that ``ShmTransport`` shares).

Sending: a small frame is joined with its header into one bytes object and written at once; a small frame sent
within ``_BURST_S`` of the previous write starts a burst, whose frames go out in one write at the end of the loop
iteration (one syscall for many frames; a lone request still leaves at once). Larger frames go out as header + parts
without joining (``writelines``: one sendmsg on uvloop and Python >= 3.12). Where the event loop keeps a reference
to a mutable buffer instead of copying it (uvloop, Python >= 3.12), ``send`` returns only once the socket took those
bytes, so callers may reuse their buffers as soon as ``send`` returns, as with every transport. ``send`` waits while
more than 1 MiB is unsent (pause_writing/resume_writing), so memory stays bounded.

A frame sent after a ``receive`` that waited is a reply and goes out at once, never into a burst: corked to the end
of the loop iteration it would wait for that loop iteration before it leaves.

Limits, for peers that are not trusted (docs/security.md), kept by the listener (``_tcp_listener``): it holds at
most ``max_connections`` connections and ``max_handshakes`` unfinished handshakes (a new one evicts the oldest once
that waited 1 s, else it is reset and ``connect`` retries), each of which must finish within
``handshake_timeout_s``. The stream buffer is anonymous memory, resident only where data has landed, so an idle
connection costs a few KiB; refusals are counted in ``rejected`` and logged at most once a second.

Outside the loop: ``try_send`` writes a small frame at once when nothing waits before it, for a caller in the
loop's thread while the loop is not running (the supervisor between calls; ``receive_blocking`` is its receiving
counterpart). Whatever it cannot do it leaves to ``send``, having sent nothing.

Reconnection: a connection that breaks stays broken (TransportBrokenError on every later call). Whoever owns it (the
bus) closes it and calls ``connect`` again, which retries with exponential backoff (``uniros_async.backoff``, from
0.005 s doubling to 0.5 s) until ``connect_timeout_s``; frames that were in flight when the connection broke are
lost, as on any TCP link. There is deliberately no reconnecting wrapper here: only the owner knows what to
resubscribe and re-send. Every connection has TCP keepalive (``KEEPALIVE_IDLE_S``), so an end that only receives
still learns within seconds that its peer's socket is gone.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import fcntl
import logging
import os
import socket
import struct
import sys
import time
from collections.abc import Sequence
from typing import Any, cast

from uniros_async.errors import AuthenticationError, FrameTooLargeError, TransportBrokenError, TransportClosedError
from uniros_async.transports._tcp_connect import open_connection
from uniros_async.transports._tcp_handshake import (
    FLAG_AUTH,
    HELLO,
    MAGIC,
    PROOF_BYTES,
    PROTOCOL_VERSION,
    TcpHandshake,
)
from uniros_async.transports._tcp_listener import TcpListener, format_uri, open_listener
from uniros_async.transports._tcp_receive import _DEAD, _FRAMES, _HANDSHAKE, TcpReceiving
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

_pack_header = struct.Struct("<I").pack
_WIRE_MAX_FRAME = 2**32 - 1  # what a u32 length prefix can announce

_JOIN_MAX_BYTES = 16 * 1024  # smaller frames are sent as one joined bytes object
_CORK_MAX_BYTES = 64 * 1024  # coalesced small frames are written once they reach this size
_BURST_S = 20e-6  # a small frame sent this soon after the previous write starts a coalesced burst
_TX_HIGH_BYTES = 1024 * 1024  # send() waits while the event loop holds more than this unsent
_TX_LOW_BYTES = 256 * 1024
KEEPALIVE_IDLE_S = 2
"""TCP keepalive: a connection idle this long is probed every ``KEEPALIVE_INTERVAL_S``, and broken after
``KEEPALIVE_PROBES`` unanswered probes. A side that only receives (a subscriber, the domain's end of a node's
registry connection) otherwise never learns that its peer's socket is gone (a reset that reached only the peer, a
peer host that restarted): the probe is answered with a reset, and the owner reconnects."""
KEEPALIVE_INTERVAL_S = 1
KEEPALIVE_PROBES = 3
RTO_MAX_MS = 1000
"""TCP's retransmission timeout, which doubles at each retransmission of a segment, stops growing here (Linux 6.15
and later; the system's 120 s elsewhere): a link that returns after an outage of any length carries the waiting data
within about a second."""
_TCP_RTO_MAX_MS = 44  # linux/tcp.h, for a Python whose socket module does not name it


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
    if sys.platform == "linux":  # the retransmission timeout capped: a link back after an outage carries data again
        with contextlib.suppress(OSError):  # within RTO_MAX_MS, not after a backoff grown to tens of seconds (<6.15)
            sock.setsockopt(socket.IPPROTO_TCP, getattr(socket, "TCP_RTO_MAX_MS", _TCP_RTO_MAX_MS), RTO_MAX_MS)


_SIOCOUTQNSD = 0x894B if sys.platform == "linux" else None  # linux/sockios.h: a tcp socket's bytes not yet sent

_CLOSE_TIMEOUT_S = 1.0  # aclose waits this long for unsent bytes to leave, then aborts

# Python 3.11's selector transport copies what it cannot send at once; uvloop and 3.12+ keep a reference instead
# (and only they send a list of buffers with one sendmsg; 3.11's writelines joins them first).
_SELECTOR_COPIES = sys.version_info < (3, 12)


def _as_bytes_view(part: Buffer) -> memoryview:
    view = memoryview(part)
    if view.ndim != 1 or view.itemsize != 1:
        view = view.cast("B")  # transports slice by bytes: a float64 or 2-D view must look like bytes
    return view


class TcpTransport(TcpReceiving, Transport):
    """One end of a TCP connection carrying length-prefixed frames.

    Made by ``connect`` or ``TcpListener.accept``; the asyncio protocol callbacks (``connection_made``,
    ``get_buffer``, ...) belong to the event loop, not to callers.
    """

    delivery = Delivery.RELIABLE
    scheme = "tcp"
    _encrypted = False  # TlsTransport: True (the socket carries ciphertext; receive never reads it itself)
    _listener: TcpListener[Any] | None

    def __init__(self, options: TransportOptions, *, listener: TcpListener[Any] | None = None, uri: str = "") -> None:
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
        self._init_receiving()
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

    def unsent_bytes(self) -> int:
        """What the event loop holds unsent, plus what the kernel holds that it has not sent (``SIOCOUTQNSD``;
        Linux); under TLS both count ciphertext."""
        tr = self._tr
        if tr is None or not self._ok:
            return 0
        n = tr.get_write_buffer_size()
        sock = tr.get_extra_info("socket")
        if sock is not None and _SIOCOUTQNSD is not None:
            with contextlib.suppress(OSError):
                n += struct.unpack("i", fcntl.ioctl(sock.fileno(), _SIOCOUTQNSD, b"\0\0\0\0"))[0]
        return n

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


async def listen(uri: str, options: TransportOptions) -> TcpListener[TcpTransport]:
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
    from 0.005 s doubling to 0.5 s, until ``options.connect_timeout_s`` has passed since the call, handshake included.
    Cancelling leaves nothing open.

    Raises:
        ConfigError: the URI has no host or port.
        TimeoutError: nobody accepted and completed the handshake within ``connect_timeout_s`` (names the URI).
        AuthenticationError: the key settings differ or the listener failed to prove the shared key.
        TransportBrokenError: the peer is not a uniros listener (or speaks another version).
    """
    return await open_connection(uri, options, TcpTransport)
