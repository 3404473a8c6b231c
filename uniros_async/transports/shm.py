"""Same-machine transport: ``shm://NAME``, two shared-memory rings per connection with eventfd wakeups.

A listener is a Unix SOCK_SEQPACKET socket in the abstract namespace (``"\\0uniros-shm-NAME"``: nothing on the
filesystem; an empty NAME picks a unique one). ``connect`` performs a handshake on it: hello, challenge (with an
HMAC-SHA256 proof of ``auth_key`` in both directions when it is set), and the listener's setup message, which carries
three descriptors (SCM_RIGHTS): a sealed memfd holding one ring per direction (see ``_shm_ring``) and two eventfds,
one doorbell per end. Nothing ever appears in /dev/shm, so nothing is left behind even after SIGKILL.

Moving a frame: the sender copies it into its ring (one copy, part by part for a multi-part frame), publishes the
write position, then, after a memory barrier, rings the peer's doorbell only if the peer's ticket says it waits.
The receiver reads without a syscall when data is there; otherwise it polls for at most ``ShmTransport.spin_ns``
(yielding the CPU between polls, and only while such polls keep paying off: ``_spin``), then sets its ticket, re-checks
(after a barrier: no lost wakeup) and awaits its doorbell, which is registered in the event loop (``loop.add_reader``).
The same holds the other way for a sender that waits for space (backpressure). An idle end costs no CPU.
A thread with nothing else to do can move frames without running the event loop: ``try_send`` writes when there
is room, ``receive_blocking`` polls the same way and then sleeps in ``poll(2)`` on the doorbell (the supervisor's
step, in the agent's thread).

``receive`` returns a read-only view straight into the ring when the frame is contiguous there (the usual case: the
writer restarts at offset 0 whenever little is in flight) and a copy when the frame wraps around the end. The space
of a view is released to the writer at the next ``receive``, so a sender waits while the ring (``ring_bytes``, the
larger of the two ends' values) lacks room for its frame next to the frame the reader still holds. Frames larger
than the ring are streamed through it in chunks, which needs the peer to be receiving meanwhile, as on TCP.
The Unix socket stays open for the life of the connection: EOF on it means the peer is gone, and ``receive`` then
raises TransportBrokenError once everything the peer sent has been delivered.

The peer is trusted with the shared memory once admitted (it can write to both rings); ``auth_key`` decides who is
admitted. ``bind_host`` does not apply.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import mmap
import os
import select
import socket
import struct
from collections.abc import AsyncIterator, Callable, Sequence
from typing import Any

from uniros_async.errors import (
    FrameTooLargeError,
    TransportBrokenError,
    TransportClosedError,
)
from uniros_async.transports import _shm_handshake
from uniros_async.transports._shm_ring import (
    R_CPU,
    R_POS,
    R_TICKET,
    SKIP,
    W_POS,
    W_TICKET,
    RingViews,
    ring_end_class,
)
from uniros_async.transports._shm_ring import fence_acquire as _fence_acquire
from uniros_async.transports._shm_ring import fence_release as _fence_release
from uniros_async.transports._shm_slow import Partial, ShmSlowPaths, as_parts
from uniros_async.transports._shm_socket import ShmListener, open_shm_connection, open_shm_listener
from uniros_async.transports._spin import SHARED_CORE_NS, SPIN_CREDIT, SPIN_EXTRA_NS, SpinCredit, now_ns, this_cpu
from uniros_async.transports.base import (
    Buffer,
    Delivery,
    Transport,
    TransportOptions,
    TransportStats,
)

__all__ = ["ShmListener", "ShmTransport", "connect", "listen"]

logger = logging.getLogger(__name__)


# The poll before a sleep (the rule of ``_spin``): module globals, which a poll reads every time.
_now_ns = now_ns
_SPIN_CREDIT = SPIN_CREDIT
_SPIN_EXTRA_NS = SPIN_EXTRA_NS
_this_cpu = this_cpu
_NEVER_NS = (1 << 63) - 1  # a look_at_ns for RingEnd.poll that never comes
_HANG_UP = getattr(select, "POLLRDHUP", 0x2000)  # poll(2): the peer closed its end (POLLHUP, POLLERR: always reported)


class ShmTransport(SpinCredit, Transport, ShmSlowPaths):
    """One end of a ``shm://`` connection (made by ``connect`` or ``ShmListener.accept``).

    Costs: one copy per send (cheapest when the ring's pages are in cache), no syscall per frame while both ends
    are busy, one eventfd write when the reader sleeps (figures: docs/performance.md).
    """

    delivery = Delivery.RELIABLE
    scheme = "shm"
    spin_ns: int = 50_000
    """How long receive() polls before it sleeps (plus a margin after large sends); 0 disables spinning, also when
    set on an open connection. Spinning holds the event loop, so other tasks of this loop wait up to this long; it
    never happens when both ends are in the same process."""

    on_shared_core: Callable[[int], None] | None = None
    """Called with the CPU when this end, about to poll for the peer's next frame, finds the peer on its own core
    (``_peer_here``): a worker moves itself off it (``runtime.worker``); the agent's process is left where it is."""

    def __init__(
        self,
        *,
        name: str,
        sock: socket.socket,
        setup: _shm_handshake.Setup,
        options: TransportOptions,
    ) -> None:
        super().__init__()
        self._loop = asyncio.get_running_loop()
        self._name = name
        self._sock = sock
        self._mm: mmap.mmap | None = setup.mm
        self._cap = cap = setup.cap
        self._max_frame = options.max_frame_bytes
        self._doorbell = setup.doorbell_fd
        self._peer_doorbell = setup.peer_doorbell_fd
        self._base = memoryview(setup.mm)
        self._rx = RingViews(self._base, cap, setup.rx_index)
        self._tx = RingViews(self._base, cap, 1 - setup.rx_index)
        self._rx_ctl, self._tx_ctl = self._rx.ctl, self._tx.ctl
        # positions, counters and the usual path of a frame (compiled where it is built; _shm_ring.RingEnd)
        self._ring = ring = ring_end_class()(self._rx, self._tx, options.max_frame_bytes, setup.peer_doorbell_fd)
        self.stats = _RingStats(ring)
        self._rx_ticket = 0
        self._tx_ticket = 0
        self._rx_waiter: asyncio.Future[None] | None = None
        self._poller: select.poll | None = None  # receive_blocking's, made on first use
        self._tx_waiter: asyncio.Future[None] | None = None
        self._loaned = False  # a loan() block is writing the next frame in place
        self.frames_loaned = 0
        """Frames sent in place (``loan``): the ring holds them as written; the others were copied into it."""
        self._rx_partial: Partial | None = None
        self._tx_stream: asyncio.Task[None] | None = None
        self._peer_gone = False
        self._broken: str | None = None
        self._closed = False
        # ring.rx_fast: not closed, not broken, no streamed frame half-received;
        # ring.tx_fast: not closed, not broken, peer not gone, no streamed frame being finished, no loan open
        try:
            pid = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, 12))[0]
        except OSError:
            pid = 0
        self._peer_desc = f"shm://{name} (pid {pid})"
        # the writer in this process is likely on this very event loop: spinning cannot help
        self._spin_allowed = self.spin_ns > 0 and pid != os.getpid()
        self._spin_credit = _SPIN_CREDIT if self._spin_allowed else 0
        self._woken = False  # woken from a wait since the last poll, with a way to move (_look_after_wake_up)
        self._loop.add_reader(self._doorbell, self._on_doorbell)
        self._loop.add_reader(sock.fileno(), self._on_socket)

    @property
    def max_frame_bytes(self) -> int:
        return self._max_frame

    @property
    def peer(self) -> str:
        return self._peer_desc

    # ------------------------------------------------------------------------------------------------ receiving

    async def receive(self) -> memoryview:
        """Wait for the next frame: a read-only view into the ring (valid until the next ``receive``) or a copy.

        Cancelling leaves no frame half-read: a streamed frame's progress is kept for the next call.

        Raises:
            TransportClosedError: this end was closed.
            TransportBrokenError: the peer is gone (after every frame it sent was delivered) or broke the protocol.
        """
        view = self._ring.take_ready()  # the common case: a whole frame, contiguous in the ring, is already there
        if view is not None:
            return view
        return await self._receive_slow()

    async def _receive_slow(self) -> memoryview:
        if self._closed:
            raise TransportClosedError(f"receive on closed transport to {self.peer}")
        if self._broken is not None:
            raise TransportBrokenError(self._broken)
        ring = self._ring
        if ring.rpos != ring.rx_released:
            ring.release_rx()
        ctl = self._rx.ctl
        while True:
            gone = self._peer_gone  # read before the position: the peer wrote everything before it hung up
            avail = ctl[W_POS] - ring.rpos
            if avail:
                view = ring.take_ready()  # the usual frame, taken by the ring end; else the cases _take handles
                if view is None:
                    view = self._take(avail)
                if view is not None:
                    return view
            elif gone:
                what = "in the middle of a frame" if self._rx_partial is not None else "the connection"
                raise TransportBrokenError(f"peer {self.peer} closed {what}")
            else:
                if self._woken:  # the first poll since a wake-up (_wait_readable): see _look_after_wake_up
                    self._look_after_wake_up()
                window_ns = self._window_ns()
                if self._spin_credit > 0 and self.spin_ns and self._spin(window_ns):
                    continue  # (polled here, not in _wait_readable: a coroutine less per frame that a poll catches)
                await self._wait_readable(window_ns)
                self._woken = self.on_shared_core is not None

    def _window_ns(self) -> int:
        """How long to poll for the next frame: ``spin_ns``, plus, after a large send, the time the peer needs to
        read it (~0.1 ns per byte across cores) before it can answer."""
        ring = self._ring
        window_ns = self.spin_ns + min(ring.sent_since_wait // 10, _SPIN_EXTRA_NS)
        ring.sent_since_wait = 0
        return window_ns

    def _peer_here(self) -> bool:
        """Whether the peer, when it last looked, ran on the CPU this end polls on (and say where this end runs).

        The two ends of a connection publish where they wait (``R_CPU``), and an end that finds the peer on its own
        core stops polling (``_spin`` says why): a shared core then costs two context switches per exchange, not a
        scheduler slice. An end looks only once a poll has lasted ``SHARED_CORE_NS`` (a quick exchange never pays
        for the look), and says where it runs when it looks and, at most once a millisecond, when it sends: a hint
        (a process seldom changes cores), which also covers an end that never polls long (its replies are there
        before it looks, because the peer preempted it on the shared core).
        """
        cpu = _this_cpu() + 1
        self._rx_ctl[R_CPU] = cpu
        if cpu == 0 or self._tx_ctl[R_CPU] != cpu:
            return False
        if self.on_shared_core is None:
            return True
        self.on_shared_core(cpu - 1)  # moves this end elsewhere, if it can
        moved = _this_cpu() + 1
        self._rx_ctl[R_CPU] = moved
        return bool(moved == cpu)

    def _look_after_wake_up(self) -> None:
        """Look where the peer runs (``_peer_here``, which moves this end off the peer's core where it can), once
        after a wake-up, before the first poll for the next frame. A wake-up is where the scheduler places this end
        anew, and it often puts it on the core of the peer that woke it: there the two take turns (each poll yields
        the core to the other) while the other core idles, every exchange a pair of context switches, and no poll
        lasts long enough to look (``SHARED_CORE_NS``). Looked for here, after the frame that woke it has been
        answered, so that moving does not delay that answer: a peer whose wait for it ran out would sleep, and be
        woken onto this end's new core in turn."""
        self._woken = False
        self._peer_here()

    def _spin(self, window_ns: int) -> bool:
        """Poll for data past our read position for up to ``window_ns``, yielding the CPU between polls
        (``RingEnd.poll``); True if it came. Looks where the peer runs once the poll has lasted ``SHARED_CORE_NS``
        (``_peer_here``) and gives up at once if it shares this core. Keeps the spin credit (``_spin.SpinCredit``)."""
        start = _now_ns()
        deadline = start + window_ns
        got = self._ring.poll(deadline, start + SHARED_CORE_NS)
        if got == 2:  # a poll this long: is the peer waiting for this very core?
            if self._peer_here():
                return False
            got = self._ring.poll(deadline, _NEVER_NS)
        if got == 1:
            self._spin_credit = _SPIN_CREDIT
            return True
        self._spin_credit -= 1
        return False

    async def _wait_readable(self, window_ns: int) -> None:
        """Sleep until the peer publishes more than we have read (or hangs up, or we close); ``window_ns``: how long
        the poll before it was (see ``_waited``)."""
        ctl = self._rx.ctl
        ticket = self._rx_ticket + 1
        ctl[R_TICKET] = ticket  # odd: "I am about to sleep; ring my doorbell"
        _fence_acquire()
        _fence_release()
        try:
            if ctl[W_POS] == self._ring.rpos and not self._peer_gone:  # re-check after the fence: no lost wakeup
                fut = self._rx_waiter = self._loop.create_future()
                t0 = _now_ns()
                try:
                    await fut
                finally:
                    self._rx_waiter = None
                self._waited(t0, window_ns)
        finally:
            self._rx_ticket = ticket + 1
            if not self._closed:
                ctl[R_TICKET] = ticket + 1
        if self._closed:
            raise TransportClosedError(f"transport to {self.peer} was closed")

    def receive_blocking(self, timeout_s: float, watch: Sequence[int] = ()) -> memoryview | None:
        """``receive`` in the calling thread, outside the event loop, for a caller that has nothing else to do
        meanwhile (the agent's thread waiting for its workers' replies): polls as ``receive`` does, then blocks in
        ``poll(2)`` on the doorbell for at most ``timeout_s``. Costs no event-loop round: the counterpart of
        ``try_send``. This transport's event loop must not be running a ``receive`` meanwhile.

        Returns the frame as ``receive`` would, or None when it cannot be had here: nothing came within
        ``timeout_s``, the control socket has news (the peer hung up), the next frame needs the slow path (wrapped
        around the ring's end or streamed), or this end is closed or broken. Nothing was consumed then, and
        ``receive`` must be awaited (it delivers the frame or raises what is wrong). ``watch``: other connections'
        socket descriptors; one hung up or reset while this waits (POLLRDHUP, POLLHUP, POLLERR) returns None too.
        """
        ring = self._ring
        if not ring.rx_fast:
            return None
        view = ring.take_ready()
        if view is not None:
            return view
        ctl = self._rx_ctl
        if ctl[W_POS] != ring.rpos:  # it came just now, or it is something only the slow path takes
            return ring.take_ready()
        deadline = _now_ns() + int(timeout_s * 1e9)
        window_ns = self._window_ns()
        if self._spin_credit > 0 and self.spin_ns and self._spin(window_ns):
            return ring.take_ready()
        if not ring.rx_fast:  # closed (or broken) while it polled
            return None
        poller = self._poller
        if poller is None:
            poller = self._poller = select.poll()
            poller.register(self._doorbell, select.POLLIN)
            poller.register(self._sock.fileno(), select.POLLIN)
        for other in watch:
            poller.register(other, _HANG_UP)
        ticket = self._rx_ticket + 1
        ctl[R_TICKET] = ticket  # odd: "I am about to sleep; ring my doorbell"
        _fence_acquire()
        _fence_release()
        t0 = _now_ns()
        try:
            while ctl[W_POS] == ring.rpos:  # re-checked after the fence: no lost wakeup
                left_ns = deadline - _now_ns()
                if left_ns <= 0:
                    return None
                for fd, _ in poller.poll(-(-left_ns // 1_000_000)):
                    if fd != self._doorbell or self._closed:
                        return None  # the control socket (EOF or stray bytes, which _on_socket handles), or closed
                    try:
                        os.eventfd_read(fd)
                    except BlockingIOError:
                        pass
            self._waited(t0, window_ns)
        finally:
            self._rx_ticket = ticket + 1
            if not self._closed:
                ctl[R_TICKET] = ticket + 1
            for other in watch:
                poller.unregister(other)
        return ring.take_ready()

    # -------------------------------------------------------------------------------------------------- sending

    async def send(self, frame: Buffer | Sequence[Buffer]) -> None:
        """Copy one frame (a buffer or a sequence of buffers) into the ring, waiting for space if it is full.

        If cancelled while waiting for space, nothing was sent. A frame larger than the ring is streamed; if that
        is cancelled half-way, the rest is sent in the background (from a copy) so that no half frame is left.

        Raises:
            TransportClosedError: this end was closed.
            TransportBrokenError: the peer is gone or broke the protocol.
            FrameTooLargeError: the frame is over ``max_frame_bytes``; nothing was sent.
        """
        one: Buffer | None
        parts: Sequence[Buffer]
        if type(frame) is bytes or type(frame) is bytearray:
            one, parts = frame, ()
            n = len(frame)
        elif type(frame) is memoryview and frame.format == "B" and frame.ndim == 1:
            one, parts = frame, ()
            n = len(frame)
        else:
            one, parts = None, as_parts(frame)
            n = sum(len(p) for p in parts)
        ring = self._ring
        if one is not None and ring.try_send(one):  # the usual case: room, a healthy end, a frame that fits
            return
        if not ring.tx_fast:
            await self._send_checks()
        if n > self._max_frame:
            raise FrameTooLargeError(f"frame of {n} bytes exceeds max_frame_bytes={self._max_frame}")
        cap = self._cap
        rec = 8 + ((n + 7) & ~7)
        if rec > cap:
            await self._send_streamed(parts if one is None else (one,), n)
            return
        while (place := ring.place(rec)) is None:
            await self._wait_writable(rec)
            if not ring.tx_fast:
                await self._send_checks()
        self._write(parts if one is None else (one,), n, rec, *place)

    def try_send(self, frame: bytes) -> bool:
        """Send ``frame`` at once if that needs no waiting (the common case: room in the ring, an open and healthy
        connection, a frame that fits the ring); True if it was sent. False: nothing was sent, ``send`` must do it
        (it waits for room, or raises what is wrong). Lets a caller outside the event loop send without running it.
        """
        return self._ring.try_send(frame)

    def lends(self, nbytes: int) -> bool:
        """Whether ``loan(nbytes)`` lends the ring's own memory (the frame fits the ring) rather than a buffer."""
        return 0 <= nbytes <= self._max_frame and 8 + ((nbytes + 7) & ~7) <= self._cap

    @contextlib.asynccontextmanager
    async def loan(self, nbytes: int) -> AsyncIterator[memoryview]:
        """The next frame's own place in the ring, ``nbytes`` long: write it in the block, and it is sent when the
        block ends, without a copy (a renderer draws straight into it). Waits for room as ``send`` does. If the
        block raises, nothing is sent. A frame larger than the ring is lent from a buffer of our own and streamed
        (one copy). Nothing else may be sent on this end during the block; the view must not be used after it.

        Raises:
            TransportClosedError, TransportBrokenError, FrameTooLargeError: as ``send``.
        """
        ring = self._ring
        if not ring.tx_fast:
            await self._send_checks()
        if nbytes < 0 or nbytes > self._max_frame:
            raise FrameTooLargeError(f"frame of {nbytes} bytes exceeds max_frame_bytes={self._max_frame}")
        rec = 8 + ((nbytes + 7) & ~7)
        if rec > self._cap:
            async with super().loan(nbytes) as view:
                yield view
            return
        while (place := ring.place(rec)) is None:
            await self._wait_writable(rec)
            if not ring.tx_fast:
                await self._send_checks()
        off, skip = place
        start = (0 if skip else off) + 8
        view = self._tx.data[start : start + nbytes]
        self._loaned = True
        ring.tx_fast = False
        try:
            yield view
        finally:
            self._loaned = False
            ring.tx_fast = not (self._closed or self._broken is not None or self._peer_gone)
            with contextlib.suppress(BufferError):  # the caller still holds views of it: theirs to drop
                view.release()
        if not ring.tx_fast:
            await self._send_checks()  # closed or broken during the block: raises, nothing is sent
        data_q = self._tx.data_q
        if skip:
            data_q[off >> 3] = SKIP
            off = 0
        data_q[off >> 3] = nbytes
        ring.commit(nbytes, rec, skip)
        self.frames_loaned += 1

    def _write(self, parts: Sequence[Buffer], n: int, rec: int, off: int, skip: int) -> None:
        """Copy the frame's ``parts`` to the place ``RingEnd.place`` gave, publish it, and ring the reader if it
        sleeps. (A single buffer that has room at once goes through ``RingEnd.try_send`` instead.)"""
        cap = self._cap
        data_q = self._tx.data_q
        if skip:
            data_q[off >> 3] = SKIP
            off = 0
        data_q[off >> 3] = n
        data = self._tx.data
        pos = off + 8
        for part in parts:
            if pos == cap:
                pos = 0
            k = len(part)
            end = pos + k
            if end <= cap:
                data[pos:end] = part
                pos = end
            else:
                first = cap - pos
                view = part if type(part) is memoryview else memoryview(part)
                data[pos:] = view[:first]
                data[: k - first] = view[first:]
                pos = k - first
        self._ring.commit(n, rec, skip)

    async def _send_checks(self) -> None:
        """The slow path of send(): finish a cancelled streamed frame, then raise if the connection is unusable."""
        if self._closed:
            raise TransportClosedError(f"send on closed transport to {self.peer}")
        if self._loaned:
            raise RuntimeError(f"a loaned frame to {self.peer} is still being written: send after its block ends")
        if self._tx_stream is not None:
            await self._join_stream()
        if self._closed:
            raise TransportClosedError(f"send on closed transport to {self.peer}")
        if self._broken is not None:
            raise TransportBrokenError(self._broken)
        if self._peer_gone:
            raise TransportBrokenError(f"peer {self.peer} closed the connection")

    async def _wait_writable(self, need: int) -> None:
        """Sleep until the reader leaves ``need`` bytes free (or hangs up, or we close)."""
        ctl = self._tx.ctl
        ticket = self._tx_ticket + 1
        ctl[W_TICKET] = ticket
        _fence_acquire()
        _fence_release()
        try:
            if self._cap - (self._ring.wpos - ctl[R_POS]) < need and not self._peer_gone:
                fut = self._tx_waiter = self._loop.create_future()
                try:
                    await fut
                finally:
                    self._tx_waiter = None
        finally:
            self._tx_ticket = ticket + 1
            if not self._closed:
                ctl[W_TICKET] = ticket + 1
        if self._closed:
            raise TransportClosedError(f"transport to {self.peer} was closed")

    # --------------------------------------------------------------------------------------- events and closing

    def _on_doorbell(self) -> None:
        try:
            os.eventfd_read(self._doorbell)
        except BlockingIOError:
            pass
        self._wake()

    def _on_socket(self) -> None:
        try:
            data = self._sock.recv(16)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if data:  # nothing is sent on it after the handshake
            self._fail(f"peer {self.peer} sent {len(data)} unexpected bytes on the control socket")
            return
        self._peer_gone = True
        self._ring.tx_fast = False
        self._loop.remove_reader(self._sock.fileno())
        self._wake()

    def _wake(self) -> None:
        for fut in (self._rx_waiter, self._tx_waiter):
            if fut is not None and not fut.done():
                fut.set_result(None)

    def _fail(self, reason: str) -> TransportBrokenError:
        """Mark the connection broken (the peer broke the protocol) and tell the peer by hanging up."""
        self._broken = reason
        self._ring.rx_fast = self._ring.tx_fast = False
        logger.warning("%s", reason)
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._wake()
        return TransportBrokenError(reason)

    async def aclose(self) -> None:
        """Close this end (idempotent): blocked ``receive``/``send`` get TransportClosedError, the peer sees a
        clean close after draining what we sent. Views returned by ``receive`` stay readable until dropped."""
        if self._closed:
            return
        self._closed = True
        self._ring.close()  # (also stops its fast paths)
        self._loop.remove_reader(self._doorbell)
        if not self._peer_gone:
            self._loop.remove_reader(self._sock.fileno())
        self._wake()
        task = self._tx_stream
        if task is not None:
            task.cancel()
            await asyncio.wait({task})
        self._sock.close()
        os.close(self._doorbell)
        os.close(self._peer_doorbell)
        with contextlib.suppress(BufferError):  # the ring end still holds them: a receive_blocking in another
            self._rx.release()  # thread is polling (RingEnd.close leaves them to it); they go with the last user
            self._tx.release()
            self._base.release()
        mm, self._mm = self._mm, None
        try:
            if mm is not None:
                mm.close()
        except BufferError:
            pass  # a frame view handed out by receive() is still alive; the mapping goes with the last one


class _RingStats(TransportStats):
    """An shm end's counters: the four frame and byte counts are its ``RingEnd``'s, which its hot paths keep."""

    def __init__(self, ring: Any) -> None:  # (no dataclass __init__: the counts are properties)
        self._ring = ring
        self.rejected = 0

    frames_sent = property(lambda self: self._ring.frames_sent)
    frames_received = property(lambda self: self._ring.frames_received)
    bytes_sent = property(lambda self: self._ring.bytes_sent)
    bytes_received = property(lambda self: self._ring.bytes_received)


# --------------------------------------------------------------------------------------------- entry points


async def listen(uri: str, options: TransportOptions) -> ShmListener[ShmTransport]:
    """Listen at ``shm://NAME`` (an empty NAME picks a unique one).

    Raises:
        ConfigError: NAME is already listening on this machine (in this network namespace), or is invalid.
    """
    return await open_shm_listener(uri, options, ShmTransport)


async def connect(uri: str, options: TransportOptions) -> ShmTransport:
    """Connect to ``shm://NAME``, retrying with backoff until it listens, for up to ``connect_timeout_s``.

    Raises:
        ConfigError: the URI has no NAME.
        TimeoutError: nobody listened and answered within ``connect_timeout_s``.
        AuthenticationError: the listener refused our key, or failed to prove its own.
        TransportBrokenError: the listener broke the handshake; ``__cause__`` holds the OSError if any.
    """
    return await open_shm_connection(uri, options, ShmTransport)
