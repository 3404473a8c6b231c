"""shm://'s RingEnd: the compiled class (``_shm_ring_c``) does what the pure-Python reference does, operation by
operation, on real memfd segments and real eventfd doorbells; and a connection uses the one it is told to."""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from uniros_async.testing.transport_contract import open_pair
from uniros_async.transports import _shm_ring
from uniros_async.transports._shm_ring import (
    PURE_PYTHON_ENV,
    R_CPU,
    R_TICKET,
    W_TICKET,
    RingEnd,
    RingViews,
    compiled_ring_end,
    create_segment,
    describe_ring_end,
)

CAP = 4 * 4096  # four pages: frames wrap, skip to the start, fill the ring, and large ones restart at offset 0


def test_the_compiled_ring_end_is_built_and_shares_the_layout() -> None:
    """``pip install -e .`` builds the C extension here (gcc is on these machines); its constants are the layout's."""
    compiled = compiled_ring_end()
    assert compiled is not None, "uniros_async/transports/_shm_ring_c.c was not built: is gcc installed?"
    from uniros_async.transports import _shm_ring_c  # type: ignore[attr-defined]

    for name in ("W_POS", "R_POS", "R_TICKET", "W_TICKET", "R_CPU", "RESTART_BYTES", "CPU_HINT_NS"):
        assert getattr(_shm_ring_c, name) == getattr(_shm_ring, name), name


class _Pair:
    """Two ends (``a`` sends, ``b`` receives) of one segment, with a RingEnd class, and their doorbells."""

    def __init__(self, cls: Any, cls_b: Any = None) -> None:
        self.fd, self.mm = create_segment(CAP)
        base = memoryview(self.mm)
        self.views = [RingViews(base, CAP, 0), RingViews(base, CAP, 1)]
        self.bell_a, self.bell_b = os.eventfd(0, os.EFD_NONBLOCK), os.eventfd(0, os.EFD_NONBLOCK)
        # a receives on ring 0 and sends on ring 1; each rings the other's doorbell
        self.a = cls(self.views[0], self.views[1], 1 << 20, self.bell_b)
        self.b = (cls_b or cls)(self.views[1], self.views[0], 1 << 20, self.bell_a)
        self.base = base

    def rings(self, fd: int) -> int:
        try:
            return os.eventfd_read(fd)
        except BlockingIOError:
            return 0

    def close(self) -> None:
        self.a.close()
        self.b.close()
        for v in self.views:
            v.release()
        self.base.release()
        self.mm.close()
        for fd in (self.fd, self.bell_a, self.bell_b):
            os.close(fd)


@contextlib.contextmanager
def _pairs() -> Iterator[tuple[_Pair, ...]]:
    """Both ends compiled, both Python, and a compiled sender with a Python receiver (one layout, two languages)."""
    compiled = compiled_ring_end()
    assert compiled is not None
    pairs = (_Pair(compiled), _Pair(RingEnd), _Pair(compiled, RingEnd))
    try:
        yield pairs
    finally:
        for pair in pairs:
            pair.close()


STATE = ("wpos", "rpos", "rx_released", "signaled_reader", "signaled_writer", "sent_since_wait")
COUNTS = ("frames_sent", "bytes_sent", "frames_received", "bytes_received")

ops = st.lists(
    st.one_of(
        # small frames (the step path's), large ones (over RESTART_BYTES), up to a whole ring (some cannot go)
        st.tuples(st.just("send"), st.one_of(st.integers(0, 64), st.integers(4000, 8000), st.integers(0, CAP))),
        st.tuples(st.just("take"), st.just(0)),
        st.tuples(st.just("reader_sleeps"), st.just(0)),  # b's ticket odd: a's next publish must ring b
        st.tuples(st.just("writer_sleeps"), st.just(0)),  # a's ticket odd: b's next release must ring a
        st.tuples(st.just("place"), st.integers(8, CAP + 8)),
    ),
    max_size=60,
)


@settings(max_examples=300, deadline=None)
@given(ops)
def test_compiled_and_python_ring_ends_agree_operation_by_operation(seq: list[tuple[str, int]]) -> None:
    """The same operations on both classes, and on a compiled sender with a Python receiver, give the same results,
    state, counters and doorbell rings; and every frame taken is the frame sent, in order (frames wrap around the
    ring's end, skip to its start, fill it)."""
    with _pairs() as pairs:
        sent: list[bytes] = []
        taken = 0
        tickets = [0, 0]
        for step, (op, arg) in enumerate(seq):
            got = []
            for pair in pairs:
                if op == "send":
                    frame = bytes((step + i) % 251 for i in range(arg))
                    got.append(pair.a.try_send(frame))
                elif op == "take":
                    view = pair.b.take_ready()
                    got.append(None if view is None else bytes(view))
                    if view is not None:
                        view.release()
                elif op == "reader_sleeps":
                    pair.views[1].ctl[R_TICKET] = tickets[0] * 2 + 1  # ring 1 is b's rx ring
                    got.append(None)
                elif op == "writer_sleeps":
                    pair.views[1].ctl[W_TICKET] = tickets[1] * 2 + 1  # ... and a's tx ring
                    got.append(None)
                else:
                    got.append(pair.a.place(arg))
                got.append((pair.rings(pair.bell_a), pair.rings(pair.bell_b)))
                got.append(tuple(getattr(end, k) for end in (pair.a, pair.b) for k in STATE + COUNTS))
            if op == "reader_sleeps":
                tickets[0] += 1
            if op == "writer_sleeps":
                tickets[1] += 1
            k = len(got) // len(pairs)
            each = [got[i * k : i * k + k] for i in range(len(pairs))]
            assert each[0] == each[1] == each[2], f"step {step} ({op} {arg}): compiled, python, mixed: {each}"
            if op == "send" and got[0]:
                sent.append(bytes((step + i) % 251 for i in range(arg)))
            if op == "take" and got[0] is not None:
                assert got[0] == sent[taken], f"frame {taken} came back changed"
                taken += 1


def test_poll_reports_data_the_look_and_the_deadline() -> None:
    """``poll`` returns 1 at once when a frame is there, 2 after ``look_at_ns``, 0 after ``deadline_ns``: both."""
    with _pairs() as pairs:
        for pair in pairs:
            never = (1 << 63) - 1  # (each check alone: a preempted poll may pass both times at once)
            now = time.perf_counter_ns()
            assert pair.b.poll(never, now + 1_000_000) == 2
            assert time.perf_counter_ns() - now >= 1_000_000
            now = time.perf_counter_ns()
            assert pair.b.poll(now + 1_000_000, never) == 0
            assert time.perf_counter_ns() - now >= 1_000_000
            assert pair.a.try_send(b"here")
            now = time.perf_counter_ns()
            assert pair.b.poll(now + 10**9, now + 10**9) == 1
            assert time.perf_counter_ns() - now < 10**8


def test_a_sender_says_where_it_runs_and_a_closed_end_moves_nothing() -> None:
    """A commit writes 1 + this CPU into the sender's rx ctl (``R_CPU``); after ``close`` neither class takes
    or sends, and the compiled one lets go of the segment's buffers (the mapping can then close)."""
    with _pairs() as pairs:
        for pair in pairs:
            assert pair.a.try_send(b"x")
            assert pair.views[0].ctl[R_CPU] >= 1  # 1 + a CPU (0: not known)
            pair.a.close()
            pair.b.close()
            assert pair.a.try_send(b"y") is False
            assert pair.b.take_ready() is None


def test_a_frame_over_max_frame_or_the_ring_is_left_to_send() -> None:
    """``try_send`` leaves what it cannot send whole to ``send``: over ``max_frame``, larger than the ring."""
    with _pairs() as pairs:
        for pair in pairs:
            assert pair.a.try_send(bytes(CAP)) is False  # with its header, more than the ring
            small = type(pair.a)(pair.views[0], pair.views[1], 16, pair.bell_b)
            assert small.try_send(bytes(17)) is False and small.try_send(bytes(16)) is True
            small.close()


@pytest.mark.parametrize("pure", [False, True])
async def test_a_connection_uses_the_ring_end_it_is_told_to(pure: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """``UNIROS_SHM_PURE_PYTHON`` picks the Python class for new connections; otherwise the compiled one."""
    if pure:
        monkeypatch.setenv(PURE_PYTHON_ENV, "1")
    else:
        monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
    async with open_pair("shm://") as (a, b, _):
        async with asyncio.timeout(10):
            expected = RingEnd if pure else compiled_ring_end()
            assert type(a._ring) is expected and type(b._ring) is expected  # type: ignore[attr-defined]
            await a.send(b"ping")
            assert bytes(await b.receive()) == b"ping"
            assert a.stats.frames_sent == 1 and b.stats.bytes_received == 4


def test_which_ring_end_is_in_use_is_said(monkeypatch: pytest.MonkeyPatch) -> None:
    """``describe_ring_end`` (printed by the benchmarks and ``python -m uniros_async.transports._shm_ring``) names
    the class new connections get and why."""
    monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
    assert describe_ring_end() == "compiled"
    monkeypatch.setenv(PURE_PYTHON_ENV, "1")
    assert describe_ring_end() == f"pure Python ({PURE_PYTHON_ENV} is set)"
    monkeypatch.setenv(PURE_PYTHON_ENV, "0")  # "0" and "" mean unset
    assert describe_ring_end() == "compiled"
