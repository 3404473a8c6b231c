"""Shared-memory layout of one ``shm://`` connection: a sealed memfd holding two single-producer rings.

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

__all__ = [
    "CTL_BYTES",
    "R_CPU",
    "R_POS",
    "R_TICKET",
    "SKIP",
    "W_POS",
    "W_TICKET",
    "RingViews",
    "attach_segment",
    "create_segment",
    "round_capacity",
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
