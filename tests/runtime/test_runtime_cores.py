"""A worker that finds itself on its agent's core moves off it (``ShmTransport.on_shared_core``, over tcp on
loopback ``TcpTransport._peer_here``; ``cores.move_off_core``); workers that outnumber the cores are pinned round
robin and run their steps through (``cores.shared_cores_mode``): real processes, real CPU affinity and scheduling
policy, read back from /proc."""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np
import pytest

from uniros_async.errors import ConfigError
from uniros_async.priority import STEP_SLICE_NS
from uniros_async.runtime import make_vec
from uniros_async.runtime.supervisor import REPLY_SPIN_NS
from uniros_async.transports.base import this_cpu

pytestmark = pytest.mark.skipif(
    not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2 or this_cpu() < 0,
    reason="needs CPU affinity, sched_getcpu and at least two CPUs (the CI machine has two)",
)


def _last_cpu(pid: int) -> int:
    with open(f"/proc/{pid}/stat") as f:
        return int(f.read().rsplit(")", 1)[1].split()[36])  # field 39: the CPU it last ran on


@pytest.mark.serial  # reads which core the worker runs on, which the other tests' processes move it off
@pytest.mark.parametrize("transport", ["shm", "tcp"])
def test_a_worker_placed_on_its_agents_core_moves_to_another_and_keeps_every_core_allowed(transport: str) -> None:
    """shm learns where the agent runs from the ring's shared page, tcp on loopback from /proc
    (``TcpTransport._peer_here``)."""
    cpus = os.sched_getaffinity(0)
    here = min(cpus)
    venv = make_vec(["CartPole-v1"], pad=False, transport=transport)
    pid = venv.pids[0]
    try:
        # a worker with a core of its own apart from the agent's moves off the agent's core
        assert venv._sup.workers[0].info["moves_off_agent_core"] is True
        venv.reset(seed=0)
        os.sched_setaffinity(0, {here})  # the agent (this process) stays on one core ...
        os.sched_setaffinity(pid, {here})  # ... the worker is put on the same one (it moves there once it runs) ...
        venv.step(np.array([0]))
        os.sched_setaffinity(pid, cpus)  # ... and is then allowed everywhere again
        assert _last_cpu(pid) == here
        # it looks where the agent runs once a poll for the next request has lasted 50 us, which on one core it
        # soon does (the agent cannot run while it polls, unless a yield happens to hand the core over)
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


def _unpinned(pid: int, cpus: set[int]) -> bool:
    """Whether ``pid`` may run on every one of ``cpus``. A worker that polls moves off its agent's core by pinning
    itself away and then allowing every core again (``cores.move_off_core``), two calls that a look from here can
    fall between: look until the second has been made (or 2 s have passed)."""
    deadline = time.monotonic() + 2.0
    while os.sched_getaffinity(pid) != cpus and time.monotonic() < deadline:
        time.sleep(0.001)
    return os.sched_getaffinity(pid) == cpus


def _slice_ns(pid: int) -> int | None:
    """The scheduler slice of ``pid``'s main thread (``se.slice`` in /proc/<pid>/sched), None where not shown."""
    try:
        with open(f"/proc/{pid}/sched") as f:
            for line in f:
                if line.startswith("se.slice"):
                    return int(line.split(":")[1])
    except OSError:
        pass
    return None


def _takes_a_slice() -> bool:
    """Linux 6.12 on: EEVDF takes a slice per thread (``sched_setattr``'s ``sched_runtime``)."""
    try:
        major, minor = (int(x) for x in os.uname().release.split(".")[:2])
    except ValueError:
        return False
    return (major, minor) >= (6, 12)


def test_workers_that_outnumber_the_cores_are_pinned_round_robin_and_run_their_steps_through() -> None:
    cpus = sorted(os.sched_getaffinity(0))
    n = len(cpus) + 1
    venv = make_vec(["CartPole-v1"] * n, pad=False, envs_per_worker=1)  # a process per env: more than cores
    try:
        venv.reset(seed=0)
        for k in range(10):
            obs, reward, *_ = venv.step(np.full(n, k % 2))
            assert obs.shape == (n, 4) and reward.shape == (n,)
        for i, (w, pid) in enumerate(zip(venv._sup.workers, venv.pids, strict=True)):
            assert pid is not None
            assert w.info["cores_shared"] and w.info["pinned_cpu"] == cpus[i % len(cpus)]
            assert os.sched_getaffinity(pid) == {cpus[i % len(cpus)]} and _last_cpu(pid) == cpus[i % len(cpus)]
            assert os.sched_getscheduler(pid) == os.SCHED_BATCH
            assert os.getpriority(os.PRIO_PROCESS, pid) == os.getpriority(os.PRIO_PROCESS, 0)  # its nice value kept
            if _takes_a_slice() and _slice_ns(pid) is not None:
                assert _slice_ns(pid) == STEP_SLICE_NS
            assert w.transport.spin_ns == 0  # the agent does not poll for their replies
    finally:
        venv.close()


def test_crowded_workers_replies_are_taken_last_sent_first_and_returned_in_index_order() -> None:
    import gymnasium as gym

    n = len(os.sched_getaffinity(0)) + 1
    taken: list[int] = []
    venv = make_vec(["CartPole-v1"] * n, pad=False)
    for w in venv._sup.workers:  # each worker's reply is taken through its transport's receive_blocking

        def recording(*args: object, _take: Any = w.receive_blocking, _index: int = w.index) -> object:
            taken.append(_index)
            return _take(*args)

        w.receive_blocking = recording
    bare = [gym.make("CartPole-v1") for _ in range(n)]
    try:
        obs, _ = venv.reset(seed=0)
        want = np.stack([env.reset(seed=i)[0] for i, env in enumerate(bare)])
        np.testing.assert_allclose(obs, want)
        for k in range(6):
            actions = np.array([(k + i) % 2 for i in range(n)])
            taken.clear()
            obs, reward, *_ = venv.step(actions)
            assert taken[0] == n - 1 and sorted(set(taken)) == list(range(n))  # the last sent first, each taken
            want = np.stack([env.step(int(a))[0] for env, a in zip(bare, actions, strict=True)])
            np.testing.assert_allclose(obs, want)  # each sub-env's own observation in its own row
            assert reward.shape == (n,)
    finally:
        venv.close()
        for env in bare:
            env.close()


def test_as_many_workers_as_cores_are_left_where_the_scheduler_puts_them() -> None:
    cpus = os.sched_getaffinity(0)
    venv = make_vec(["CartPole-v1"] * len(cpus), pad=False)
    try:
        venv.reset(seed=0)
        venv.step(np.zeros(len(cpus), dtype=np.int64))
        for w, pid in zip(venv._sup.workers, venv.pids, strict=True):
            assert pid is not None
            assert not w.info["cores_shared"] and w.info["pinned_cpu"] is None
            # (the policy it started with: a gymnasium env's worker may run SCHED_RR, see worker._real_time)
            assert _unpinned(pid, cpus) and os.sched_getscheduler(pid) != os.SCHED_BATCH
            assert w.transport.spin_ns == REPLY_SPIN_NS
            # no core each apart from the agent's: moving off it would land on a fellow worker's core
            assert w.info["moves_off_agent_core"] is False
        assert venv._sup._reply_rank == list(range(len(cpus)))  # their replies taken in index order
    finally:
        venv.close()


@pytest.mark.parametrize(("mode", "batch", "spin_ns"), [("through", True, 0), ("off", False, None)])
def test_uniros_shared_cores_chooses_what_crowded_workers_do(
    monkeypatch: pytest.MonkeyPatch, mode: str, batch: bool, spin_ns: int | None
) -> None:
    monkeypatch.setenv("UNIROS_SHARED_CORES", mode)
    cpus = os.sched_getaffinity(0)
    n = len(cpus) + 1
    venv = make_vec(["CartPole-v1"] * n, pad=False)
    try:
        venv.reset(seed=0)
        venv.step(np.zeros(n, dtype=np.int64))
        for w, pid in zip(venv._sup.workers, venv.pids, strict=True):
            assert pid is not None
            assert w.info["cores_shared"] == (mode == "through") and w.info["pinned_cpu"] is None
            assert _unpinned(pid, cpus) and (os.sched_getscheduler(pid) == os.SCHED_BATCH) == batch
            assert w.transport.spin_ns == (REPLY_SPIN_NS if spin_ns is None else spin_ns)
    finally:
        venv.close()


def test_a_bad_uniros_shared_cores_is_refused_by_name(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("UNIROS_SHARED_CORES", "sometimes")
    with pytest.raises(ConfigError, match=r"UNIROS_SHARED_CORES must be one of .*'off'\), got 'sometimes'"):
        make_vec(["CartPole-v1"], pad=False)
    monkeypatch.delenv("UNIROS_SHARED_CORES")
    venv = make_vec(["CartPole-v1"], pad=False)  # nothing was left half started: the next one comes up and serves
    try:
        obs, _ = venv.reset(seed=0)
        assert obs.shape == (1, 4)
    finally:
        venv.close()


def test_real_time_workers_that_outnumber_the_cores_keep_their_own_priority_and_placement() -> None:
    """A real-time env loop has its own scheduling (``priority.raise_loop_priority``): crowding changes nothing."""
    from uniros_async.transports.shm import ShmTransport

    cpus = os.sched_getaffinity(0)
    n = len(cpus) + 1
    venv = make_vec(["uniros/Rx200Reach-v0"] * n, clock="wall", action_cycle_s=0.2)
    try:
        venv.reset(seed=0)
        venv.step(np.zeros((n, 5), np.float32))
        for w, pid in zip(venv._sup.workers, venv.pids, strict=True):
            assert pid is not None
            assert w.info["realtime"] and not w.info["cores_shared"] and w.info["pinned_cpu"] is None
            assert _unpinned(pid, cpus) and os.sched_getscheduler(pid) != os.SCHED_BATCH
            assert w.transport.spin_ns == ShmTransport.spin_ns
    finally:
        venv.close()


def test_a_ray_nodes_address_counts_as_this_machine_only_when_it_is_one_of_its_own() -> None:
    """Workers of a Ray node on the agent's machine share its cores (the agent does not poll for their replies when
    they outnumber them): the node's address is one this machine can bind."""
    from uniros_async.runtime.supervisor import _local_address

    assert _local_address("127.0.0.1")
    assert not _local_address("192.0.2.1")  # TEST-NET-1 (RFC 5737): no machine's own
    assert not _local_address("")
    assert not _local_address("not an address")
