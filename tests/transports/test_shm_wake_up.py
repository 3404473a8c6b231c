"""An shm end woken from its wait looks where its peer runs before it polls again
(``ShmTransport._look_after_wake_up``): a wake-up is where the scheduler places a process anew, often on the core of
the peer that woke it. Real processes: an echo in another process, both pinned to the cores the test chooses, and
this end's ``on_shared_core`` recording what it is told (a worker's moves itself, ``runtime.cores.move_off_core``)."""

from __future__ import annotations

import asyncio
import multiprocessing as mp
import os

import pytest

from uniros_async.bench import _peers
from uniros_async.transports.base import TransportOptions, connect, this_cpu

pytestmark = pytest.mark.skipif(
    not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2 or this_cpu() < 0,
    reason="needs CPU affinity, sched_getcpu and at least two CPUs (the CI machine has two)",
)


def _looks(echo_cpu: int, my_cpu: int, rounds: int) -> list[int]:
    """Run ``rounds`` exchanges with an echo pinned to ``echo_cpu``, this thread on ``my_cpu``, this end never
    polling (``spin_ns = 0``: every reply is waited for, and woken up to); what ``on_shared_core`` was called with."""
    before = os.sched_getaffinity(0)
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_peers.serve_uniros, args=("shm://", child), daemon=True)
    told: list[int] = []
    try:
        os.sched_setaffinity(0, {echo_cpu})  # the echo inherits it
        proc.start()
        child.close()
        os.sched_setaffinity(0, {my_cpu})
        assert parent.poll(30), "the echo did not start"
        uri = parent.recv()

        async def main() -> None:
            t = await connect(uri, TransportOptions())
            t.spin_ns = 0  # no poll: each reply is slept for, so each one wakes this end
            t.on_shared_core = told.append
            try:
                async with asyncio.timeout(20):
                    for i in range(rounds):
                        await t.send(b"frame %d" % i)
                        reply = await t.receive()
                        assert bytes(reply) == b"frame %d" % i
                        await asyncio.sleep(0.002)  # more than the peer's CPU hint interval: it says where it runs
                    await t.send(_peers.STOP)
            finally:
                await t.aclose()

        asyncio.run(main())
    finally:
        os.sched_setaffinity(0, before)
        proc.join(10)
        if proc.is_alive():
            proc.kill()
            proc.join(5)
        parent.close()
    return told


def test_an_end_woken_on_its_peers_core_is_told_so_before_it_polls_again() -> None:
    here = min(os.sched_getaffinity(0))
    told = _looks(here, here, 5)
    # each receive after the first follows a wake-up (the reply before it was slept for) and looks first
    assert told and set(told) == {here}, told


def test_an_end_woken_on_a_core_of_its_own_is_left_there() -> None:
    here, other = sorted(os.sched_getaffinity(0))[:2]
    assert _looks(other, here, 5) == []
