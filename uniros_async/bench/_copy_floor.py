"""The floors of ``uniros bench transport``'s copying rows: ``memcpy``, one copy of the frame in this process, and
``copy-pingpong``, the frame copied there and back between two processes and nothing else.

A copying round trip between two processes copies the frame twice: the client into memory the echo reads, the echo into
memory the client reads. ``copy-pingpong`` does exactly that and no more: one shared buffer each way in a memfd (nothing
in /dev/shm), a sequence number each way that the other side spins on (each side on a core of its own, as in every row),
no ring, no framing, no wake-up. Each copy reads or writes lines that the other core's cache holds, so it costs more
than the ``memcpy`` floor's copy between two buffers in one core's cache; its p50 is what any copying transport's round
trip costs here at the least, and the ``shm`` row is measured against it beside the ``memcpy`` one.

The echo reaches the memfd through ``/proc/<client pid>/fd/<fd>`` (Linux), so no descriptor needs passing. It exits
on the stop word, or when no request came for ``IDLE_EXIT_S`` (its client is gone), so it never outlives the run.
"""

from __future__ import annotations

import mmap
import multiprocessing as mp
import os
import time
from multiprocessing.connection import Connection
from typing import Any

__all__ = ["CopyPingPong", "MemcpyFloor"]

IDLE_EXIT_S = 10.0
"""The echo exits after this long without a request: its client died without saying stop."""
REPLY_TIMEOUT_S = 5.0
"""The client's bound on one round trip (the echo answers in well under a millisecond)."""
_HEAD = 4096  # the sequence numbers and the frame size, each on a cache line of its own
_SEQ_TO_ECHO, _SEQ_TO_CLIENT, _SIZE = 0, 8, 16  # int64 slots, 64 bytes apart (index x 8 bytes)
_STOP = -1


def _slots(buf: mmap.mmap) -> Any:
    import numpy as np

    return np.frombuffer(buf, np.int64, count=_HEAD // 8)


def _echo(path: str, capacity: int, ready: Connection, idle_exit_s: float) -> None:
    """The echo's process: copy each frame from the client's buffer into its own, then publish the sequence."""
    fd = os.open(path, os.O_RDWR)
    try:
        buf = mmap.mmap(fd, _HEAD + 2 * capacity)
    finally:
        os.close(fd)
    view = memoryview(buf)
    seq = _slots(buf)
    a, b = _HEAD, _HEAD + capacity
    ready.send(True)
    ready.close()
    last, clock, idle_since, spins = 0, time.monotonic, time.monotonic(), 0
    while True:
        s = int(seq[_SEQ_TO_ECHO])
        if s == last:
            spins += 1
            if not spins & 0xFFF and clock() - idle_since > idle_exit_s:
                break
            continue
        if s == _STOP:
            break
        n = int(seq[_SIZE])
        view[b : b + n] = view[a : a + n]
        seq[_SEQ_TO_CLIENT] = s
        last, idle_since = s, clock()
    del seq, view
    buf.close()


class _Floor:
    """A row that is no transport: what it sends one way is as fast as its round trips back to back."""

    def rtt(self, payload: bytes, n: int) -> list[float]:
        raise NotImplementedError

    def throughput(self, payload: bytes, n: int) -> float:
        t0 = time.perf_counter()
        self.rtt(payload, n)
        return n / (time.perf_counter() - t0)


class MemcpyFloor(_Floor):
    """One numpy copy of the payload per sample, into a buffer of its size, timed as a round trip is."""

    name = "memcpy"

    def rtt(self, payload: bytes, n: int) -> list[float]:
        import numpy as np

        src = np.frombuffer(payload, np.uint8)
        dst = np.empty_like(src)
        clock, out = time.perf_counter_ns, []
        for _ in range(n):
            t0 = clock()
            np.copyto(dst, src)
            out.append((clock() - t0) / 1e3)
        return out

    def close(self) -> None:
        pass


class CopyPingPong(_Floor):
    """The two-copy floor: this process's side, with the bench's client methods; the echo is ``_echo``."""

    name = "copy-pingpong"

    def __init__(self, capacity: int, idle_exit_s: float = IDLE_EXIT_S) -> None:
        """``capacity``: the largest payload in bytes; ``idle_exit_s``: the echo's ``IDLE_EXIT_S``."""
        self._capacity = capacity
        self._fd = os.memfd_create("uniros-copy-floor", os.MFD_CLOEXEC)
        self._proc: Any = None
        try:
            os.ftruncate(self._fd, _HEAD + 2 * capacity)
            self._buf = mmap.mmap(self._fd, _HEAD + 2 * capacity)
            self._seq = _slots(self._buf)
            self._next = 0
            ctx = mp.get_context("spawn")
            parent, child = ctx.Pipe()
            path = f"/proc/{os.getpid()}/fd/{self._fd}"
            self._proc = ctx.Process(target=_echo, args=(path, capacity, child, idle_exit_s), daemon=True)
            self._proc.start()
            child.close()
            if not parent.poll(30):
                raise TimeoutError("the copy-pingpong echo did not start within 30 s")
            parent.recv()
            parent.close()
        except BaseException:
            self.close()
            raise

    def rtt(self, payload: bytes, n: int) -> list[float]:
        size = len(payload)
        if size > self._capacity:
            raise ValueError(f"a {size}-byte payload exceeds the row's buffers ({self._capacity} bytes)")
        view, seq = memoryview(self._buf), self._seq
        seq[_SIZE] = size
        clock, out = time.perf_counter_ns, []
        for _ in range(n):
            self._next += 1
            s = self._next
            t0 = clock()
            view[_HEAD : _HEAD + size] = payload
            seq[_SEQ_TO_ECHO] = s
            deadline = t0 + int(REPLY_TIMEOUT_S * 1e9)
            while seq[_SEQ_TO_CLIENT] != s:
                if clock() > deadline:
                    raise TimeoutError(f"the copy-pingpong echo did not answer within {REPLY_TIMEOUT_S} s")
            out.append((clock() - t0) / 1e3)
        return out

    def echo_pid(self) -> int | None:
        """The echo process's pid while it runs."""
        return None if self._proc is None else int(self._proc.pid)

    def echoed(self, size: int) -> bytes:
        """The last ``size`` bytes the echo copied back (what a round trip's reply holds)."""
        return bytes(self._buf[_HEAD + self._capacity : _HEAD + self._capacity + size])

    def close(self) -> None:
        proc = self._proc
        if proc is not None:
            self._seq[_SEQ_TO_ECHO] = _STOP
            proc.join(10)
            if proc.is_alive():
                proc.kill()
                proc.join(5)
            self._proc = None
        if hasattr(self, "_seq"):
            del self._seq
            self._buf.close()
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
