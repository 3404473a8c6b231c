"""A worker that finds itself on its agent's core moves off it (``ShmTransport.on_shared_core``, over tcp on
loopback ``TcpTransport._peer_here``; ``worker._move_off_core``): real processes, real CPU affinity, read back from
/proc."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from uniros_async.runtime import make_vec
from uniros_async.transports.base import this_cpu

pytestmark = pytest.mark.skipif(
    not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2 or this_cpu() < 0,
    reason="needs CPU affinity, sched_getcpu and at least two CPUs (the CI machine has two)",
)


def _last_cpu(pid: int) -> int:
    with open(f"/proc/{pid}/stat") as f:
        return int(f.read().rsplit(")", 1)[1].split()[36])  # field 39: the CPU it last ran on


@pytest.mark.parametrize("transport", ["shm", "tcp"])
def test_a_worker_placed_on_its_agents_core_moves_to_another_and_keeps_every_core_allowed(transport: str) -> None:
    cpus = os.sched_getaffinity(0)
    here = min(cpus)
    venv = make_vec(["CartPole-v1"], pad=False, transport=transport)
    pid = venv.pids[0]
    try:
        venv.reset(seed=0)
        os.sched_setaffinity(0, {here})  # the agent (this process) stays on one core ...
        os.sched_setaffinity(pid, {here})  # ... the worker is put on the same one (it moves there once it runs) ...
        venv.step(np.array([0]))
        os.sched_setaffinity(pid, cpus)  # ... and is then allowed everywhere again
        assert _last_cpu(pid) == here
        # it looks where the agent runs once a poll for the next request has lasted 50 us (tcp: 25 us), which on
        # one core it soon does (the agent cannot run while it polls, unless a yield happens to hand the core over)
        for k in range(2000):
            venv.step(np.array([k % 2]))
            if _last_cpu(pid) != here:
                break
        assert _last_cpu(pid) != here  # it moved itself off the agent's core
        obs, reward, *_ = venv.step(np.array([1]))
        assert obs.shape == (1, 4) and reward[0] in (0.0, 1.0)  # and serves as before
        # and is not pinned anywhere: the move pins it away and then allows every core again, two calls that a
        # look from here can fall between, so look until the second has been made (or 2 s have passed)
        deadline = time.monotonic() + 2.0
        while os.sched_getaffinity(pid) != cpus and time.monotonic() < deadline:
            time.sleep(0.001)
        assert os.sched_getaffinity(pid) == cpus
    finally:
        os.sched_setaffinity(0, cpus)
        venv.close()


def test_an_agent_alone_on_its_core_is_not_moved() -> None:
    """Only workers move: the agent's process, which the user owns, keeps the affinity it had."""
    cpus = os.sched_getaffinity(0)
    here = min(cpus)
    venv = make_vec(["CartPole-v1"], pad=False)
    try:
        venv.reset(seed=0)
        os.sched_setaffinity(0, {here})
        for k in range(20):
            venv.step(np.array([k % 2]))
        assert os.sched_getaffinity(0) == {here} and this_cpu() == here
    finally:
        os.sched_setaffinity(0, cpus)
        venv.close()


def test_a_tcp_worker_on_loopback_seldom_shares_its_agents_core() -> None:
    """Over tcp the worker learns where its agent runs from /proc (``TcpTransport._peer_here``): with the agent kept
    on one core, the worker is found there after only a few of 1,000 steps. Without the look the socket's sync
    wake-ups put it back there after a quarter to a half of them (257-550 in five runs here)."""
    cpus = os.sched_getaffinity(0)
    here = min(cpus)
    venv = make_vec(["CartPole-v1"], pad=False, transport="tcp")
    pid = venv.pids[0]
    try:
        venv.reset(seed=0)
        os.sched_setaffinity(0, {here})
        shared = 0
        for k in range(1000):
            venv.step(np.array([k % 2]))
            shared += _last_cpu(pid) == here
        assert shared < 150, f"the worker was on its agent's core after {shared} of 1000 steps"
    finally:
        os.sched_setaffinity(0, cpus)
        venv.close()
