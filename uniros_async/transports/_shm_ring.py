"""Shared-memory layout of one ``shm://`` connection (a sealed memfd holding two single-producer rings), and
``RingEnd``, one end's side of the two rings with a frame's usual path (its compiled twin: ``_shm_ring_c.c``).

The segment is an anonymous memfd (``os.memfd_create``), never a name in /dev/shm: the listener creates it, passes
the descriptor to the peer over the Unix socket (SCM_RIGHTS), and both map it. The memory goes away when the last
mapping does, even if both processes are SIGKILLed, and Python's resource tracker never sees it (cpython#82300).
The size is sealed (F_SEAL_SHRINK | F_SEAL_GROW), so a peer cannot truncate it under us (which would be SIGBUS).

Layout, for a capacity ``cap`` (a multiple of the page size)::

    [ctl 0 | ring 0 (cap bytes)] [ctl 1 | ring 1 (cap bytes)]     ring 0: listener -> peer, ring 1: peer -> listener

Each ctl block is one page of native uint64 words, each word on its own cache line (no false sharing):

    W_POS      bytes ever written (producer only)       R_POS   bytes ever released (consumer only)
    R_TICKET   odd while the consumer waits for data    W_TICKET  odd while the producer waits for space
    R_CPU      1 + the CPU the consumer last waited on (0: not known; a hint, see ShmTransport._peer_here)

Positions only grow, so ``W_POS - R_POS`` is the fill level and ``pos % cap`` the offset. A record is an 8-byte
header (the payload length) and the payload padded to 8 bytes, so headers never straddle the end of the ring.
A header with ``SKIP`` set tells the reader to jump to the start of the ring (the writer restarts at offset 0 when
the ring is empty, which keeps hot data in cache and frames contiguous). A record larger than ``cap`` is streamed:
the header, then the payload in chunks as the reader frees space.
"""

from __future__ import annotations

import fcntl
import mmap
import os
import threading
from collections.abc import Callable
from typing import Any

from uniros_async.transports._spin import now_ns, spin_yield, this_cpu

__all__ = [
    "CPU_HINT_NS",
    "CTL_BYTES",
    "PURE_PYTHON_ENV",
    "RESTART_BYTES",
    "R_CPU",
    "R_POS",
    "R_TICKET",
    "SKIP",
    "W_POS",
    "W_TICKET",
    "RingEnd",
    "RingViews",
    "attach_segment",
    "create_segment",
    "round_capacity",
    "compiled_ring_end",
    "describe_ring_end",
    "ring_end_class",
    "segment_bytes",
]

CTL_BYTES = mmap.PAGESIZE
# indexes into the ctl block viewed as uint64 ("Q"); 8 words = 64 bytes apart
W_POS = 0
R_POS = 8
R_TICKET = 16
W_TICKET = 24
R_CPU = 32
SKIP = 1 << 63
MAX_CAPACITY = 1 << 30
_SEALS = fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW | fcntl.F_SEAL_SEAL
RESTART_BYTES = 4096  # a record this large restarts at offset 0 when little is in flight (RingEnd.place)
CPU_HINT_NS = 1_000_000  # a sender says where it runs at most this often (a process seldom changes cores)
PURE_PYTHON_ENV = "UNIROS_SHM_PURE_PYTHON"
"""Set (to anything but "" or "0") in the environment, new connections use the pure-Python ``RingEnd`` even where
the compiled one is built: the reference for comparisons (``benchmarks/ab_shm_ring.py``) and tests."""


def round_capacity(ring_bytes: int) -> int:
    """The ring capacity actually used: ``ring_bytes`` rounded up to whole pages, at most 1 GiB."""
    page = mmap.PAGESIZE
    return min(MAX_CAPACITY, -(-ring_bytes // page) * page)


def segment_bytes(cap: int) -> int:
    return 2 * (CTL_BYTES + cap)


def create_segment(cap: int) -> tuple[int, mmap.mmap]:
    """Create and map a sealed memfd for two rings of ``cap`` bytes. The caller owns (and closes) the fd."""
    fd = os.memfd_create("uniros-shm", os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING)
    try:
        os.ftruncate(fd, segment_bytes(cap))  # zero-filled: positions and tickets start at 0
        fcntl.fcntl(fd, fcntl.F_ADD_SEALS, _SEALS)
        return fd, mmap.mmap(fd, segment_bytes(cap))
    except BaseException:
        os.close(fd)
        raise


def attach_segment(fd: int, cap: int) -> mmap.mmap:
    """Map a segment received from the listener, after checking it is a sealed memfd of the announced size.

    Raises:
        ValueError: the capacity, the size or the seals are not what the layout needs.
    """
    if cap <= 0 or cap % mmap.PAGESIZE or cap > MAX_CAPACITY:
        raise ValueError(f"ring capacity {cap} is not a positive multiple of {mmap.PAGESIZE} <= {MAX_CAPACITY}")
    size = os.fstat(fd).st_size
    if size != segment_bytes(cap):
        raise ValueError(f"segment of {size} bytes, expected {segment_bytes(cap)} for capacity {cap}")
    seals = fcntl.fcntl(fd, fcntl.F_GET_SEALS)
    if seals & _SEALS != _SEALS:
        raise ValueError(f"segment is not sealed against resizing (seals {seals:#x})")
    return mmap.mmap(fd, size)


class RingViews:
    """The memoryviews of one ring inside a mapped segment (index 0 or 1)."""

    __slots__ = ("ctl", "data", "data_q", "data_ro")

    def __init__(self, base: memoryview, cap: int, index: int) -> None:
        start = index * (CTL_BYTES + cap)
        self.ctl = base[start : start + CTL_BYTES].cast("Q")
        self.data = base[start + CTL_BYTES : start + CTL_BYTES + cap]
        self.data_q = self.data.cast("Q")  # headers, at 8-aligned offsets
        self.data_ro = self.data.toreadonly()  # what receive() hands out

    def release(self) -> None:
        for view in (self.ctl, self.data_q, self.data_ro, self.data):
            view.release()


# The memory barrier between publishing a position and reading the peer's ticket (and between setting a ticket and
# re-reading the position): an uncontended lock acquire + release runs locked instructions (sem_trywait and
# sem_post), a full fence on x86, the project's machines. Weaker memory models (aarch64) would need a real fence,
# which the compiled RingEnd has (__atomic_thread_fence).
_fence_lock = threading.Lock()
fence_acquire = _fence_lock.acquire
fence_release = _fence_lock.release
_now_ns = now_ns  # time.perf_counter_ns: CLOCK_MONOTONIC on Linux, the compiled RingEnd's clock
_yield = spin_yield
_this_cpu = this_cpu
_eventfd_write = os.eventfd_write


class RingEnd:
    """One end's side of a connection's two rings: the read side of the ring it receives on and the write side of
    the ring it sends on, with the state of both, and the operations a frame takes on its usual (hot) path.

    ``ShmTransport`` keeps everything else (waiting, streaming, errors) and reads and writes the state here. This is
    the pure-Python reference; ``_shm_ring_c.RingEnd`` (``_shm_ring_c.c``) is the same class in C, built by
    ``pip install`` where a C compiler is at hand, and used when it is (``ring_end_class``): the two take the same
    arguments, have the same attributes and do the same things, which the shm tests check on both.

    Attributes (read and written by the transport): ``wpos`` (bytes ever written to the tx ring), ``rpos`` (bytes
    ever consumed from the rx ring), ``rx_released`` (bytes given back to the peer), ``signaled_reader`` and
    ``signaled_writer`` (the peer's tickets last rung for), ``sent_since_wait``, ``cpu_said_by``, the four frame and
    byte counters, and ``rx_fast`` / ``tx_fast`` (whether ``take_ready`` / ``try_send`` may act at all).
    """

    __slots__ = (
        "_cap",
        "_max_frame",
        "_peer_doorbell",
        "_quarter",
        "_rx_ctl",
        "_rx_q",
        "_rx_ro",
        "_tx_ctl",
        "_tx_data",
        "_tx_q",
        "bytes_received",
        "bytes_sent",
        "cpu_said_by",
        "frames_received",
        "frames_sent",
        "rpos",
        "rx_fast",
        "rx_released",
        "sent_since_wait",
        "signaled_reader",
        "signaled_writer",
        "tx_fast",
        "wpos",
    )

    def __init__(self, rx: RingViews, tx: RingViews, max_frame: int, peer_doorbell: int) -> None:
        self._cap = cap = len(rx.data)
        if len(tx.data) != cap or cap % 8 or not cap:
            raise ValueError(f"rings of {cap} and {len(tx.data)} bytes: expected two of one size, a multiple of 8")
        self._max_frame = max_frame
        self._peer_doorbell = peer_doorbell
        self._quarter = cap >> 2
        self._rx_ctl, self._rx_q, self._rx_ro = rx.ctl, rx.data_q, rx.data_ro
        self._tx_ctl, self._tx_q, self._tx_data = tx.ctl, tx.data_q, tx.data
        self.rpos = self.rx_released = rx.ctl[R_POS]
        self.wpos = tx.ctl[W_POS]
        self.signaled_reader = self.signaled_writer = 0
        self.sent_since_wait = self.cpu_said_by = 0
        self.frames_sent = self.frames_received = self.bytes_sent = self.bytes_received = 0
        self.rx_fast = self.tx_fast = True

    # ---- receiving

    def take_ready(self) -> memoryview | None:
        """The next frame if ``rx_fast`` and it is already there, whole and contiguous in the ring: a read-only view
        into the ring; else None, and nothing is consumed. Gives the space of the previous frame back first."""
        if not self.rx_fast:
            return None
        rpos = self.rpos
        if rpos != self.rx_released:
            self.release_rx()
        avail = self._rx_ctl[W_POS] - rpos
        cap = self._cap
        if 0 < avail <= cap:
            off = rpos % cap
            n = self._rx_q[off >> 3]
            if n == SKIP and avail > cap - off:
                rpos += cap - off
                avail -= cap - off
                off = 0
                n = self._rx_q[0]
            if n <= self._max_frame:
                rec = 8 + ((n + 7) & ~7)
                end = off + 8 + n
                if rec <= avail and end <= cap:
                    self.rpos = rpos + rec
                    self.frames_received += 1
                    self.bytes_received += n
                    return self._rx_ro[off + 8 : end]
        return None

    def release_rx(self) -> None:
        """Give the space up to ``rpos`` back to the writer, and ring its doorbell if it waits for space."""
        self.rx_released = rpos = self.rpos
        self.signaled_writer = self._store_and_wake(self._rx_ctl, R_POS, rpos, W_TICKET, self.signaled_writer)

    def _store_and_wake(self, ctl: memoryview, word: int, value: int, ticket_word: int, signaled: int) -> int:
        """Store a position, then, after the fence, ring the peer if its ticket says it sleeps and it was not rung
        for that ticket yet (``signaled``): the store-fence-load that no lost wake-up rests on
        (``ShmTransport._wait_readable``). Returns the ticket last rung for."""
        ctl[word] = value
        fence_acquire()
        fence_release()
        ticket = ctl[ticket_word]
        if ticket & 1 and ticket != signaled:
            _eventfd_write(self._peer_doorbell, 1)
            return int(ticket)
        return signaled

    def poll(self, deadline_ns: int, look_at_ns: int) -> int:
        """Poll for data past ``rpos``, yielding the CPU between polls: 1 when it is there, 2 once the clock
        (``time.perf_counter_ns``) passes ``look_at_ns``, 0 once it passes ``deadline_ns``."""
        ctl = self._rx_ctl
        rpos = self.rpos
        while ctl[W_POS] == rpos:
            now = _now_ns()
            if now > look_at_ns:
                return 2
            if now > deadline_ns:
                return 0
            _yield()
        return 1

    # ---- sending

    def try_send(self, frame: Any) -> bool:
        """Write ``frame`` (bytes, or a 1-D memoryview of bytes) and publish it, if ``tx_fast`` and that needs no
        waiting: room in the ring, and a frame under ``max_frame_bytes`` that fits the ring whole. True if it was
        sent; False: nothing was written."""
        n = len(frame)
        if not self.tx_fast or n > self._max_frame:
            return False
        rec = 8 + ((n + 7) & ~7)
        if rec > self._cap or (place := self.place(rec)) is None:
            return False
        off, skip = place
        data_q = self._tx_q
        if skip:
            data_q[off >> 3] = SKIP
            off = 0
        data_q[off >> 3] = n
        start = off + 8
        end = start + n
        cap = self._cap
        if start == cap:  # the header took the ring's last 8 bytes
            start, end = 0, n
        if end <= cap:
            self._tx_data[start:end] = frame
        else:  # wraps around the end of the ring (the reader copies it)
            first = cap - start
            view = frame if type(frame) is memoryview else memoryview(frame)
            self._tx_data[start:] = view[:first]
            self._tx_data[: n - first] = view[first:]
        self.commit(n, rec, skip)
        return True

    def place(self, rec: int) -> tuple[int, int] | None:
        """Where a record of ``rec`` bytes goes: (ring offset, bytes skipped to the end of the ring first), or None
        while the ring lacks room."""
        cap = self._cap
        wpos = self.wpos
        used = wpos - self._tx_ctl[R_POS]
        free = cap - used
        off = wpos % cap
        tail = cap - off
        if rec >= RESTART_BYTES and tail + rec <= free and used <= self._quarter:
            # A large frame, little in flight, and room before the reader's position: restart at offset 0, so
            # the ring reuses the same pages, still in cache (a copy into cached pages is the cheaper one).
            return off, tail
        if rec <= tail and rec <= free:
            return off, 0
        if tail + rec <= free:
            return off, tail  # keep the frame contiguous (zero-copy for the reader)
        if rec <= free:
            return off, 0  # wrap around the end; the reader copies it
        return None

    def commit(self, n: int, rec: int, skip: int) -> None:
        """Publish the record of an ``n``-byte frame (``rec`` bytes, after ``skip`` bytes to the ring's end) whose
        header and data are in place, ring the reader if it sleeps, and count it. Says where this end runs (in its
        rx ctl's ``R_CPU``, for the peer's ``ShmTransport._peer_here``) at most every ``CPU_HINT_NS``."""
        self.publish(self.wpos + skip + rec)
        self.sent_since_wait += n
        self.frames_sent += 1
        self.bytes_sent += n
        now = _now_ns()
        if now > self.cpu_said_by:
            self.cpu_said_by = now + CPU_HINT_NS
            self._rx_ctl[R_CPU] = _this_cpu() + 1

    def publish(self, wpos: int) -> None:
        """Make everything up to ``wpos`` visible to the reader, then (after the fence) wake it if it sleeps."""
        self.wpos = wpos
        self.signaled_reader = self._store_and_wake(self._tx_ctl, W_POS, wpos, R_TICKET, self.signaled_reader)

    def close(self) -> None:
        """Stop both fast paths (``take_ready`` and ``try_send`` then do nothing); the compiled class also lets go of
        the ring's buffers, after which its other methods raise ValueError."""
        self.rx_fast = self.tx_fast = False


def ring_end_class() -> Callable[[RingViews, RingViews, int, int], RingEnd]:
    """The ``RingEnd`` a new connection uses: the compiled one, unless it is not built here or ``PURE_PYTHON_ENV``
    says otherwise."""
    if _pure_python_asked():
        return RingEnd
    compiled = compiled_ring_end()
    return RingEnd if compiled is None else compiled


def _pure_python_asked() -> bool:
    return os.environ.get(PURE_PYTHON_ENV, "") not in ("", "0")


def compiled_ring_end() -> Any:
    """``_shm_ring_c.RingEnd``, or None where the extension was not built (no C compiler at install time)."""
    try:
        from uniros_async.transports import _shm_ring_c  # type: ignore[attr-defined]
    except ImportError:
        return None
    return _shm_ring_c.RingEnd


def describe_ring_end() -> str:
    """Which ``RingEnd`` new connections use here, and why, in a few words (the benchmarks print it)."""
    if _pure_python_asked():
        return f"pure Python ({PURE_PYTHON_ENV} is set)"
    if compiled_ring_end() is None:
        return "pure Python (_shm_ring_c is not built: reinstall with a C compiler for the compiled one)"
    return "compiled"


if __name__ == "__main__":  # python -m uniros_async.transports._shm_ring
    print(f"shm:// ring end: {describe_ring_end()}")
