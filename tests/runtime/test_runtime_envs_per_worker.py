"""``make_vec(envs_per_worker=K)``: one worker process hosts K consecutive envs, each over its own connection, on
its one event loop. Real worker processes: their pids, CPU affinity, a SIGKILL and what is left after close."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest
from _processes import pid_alive

from uniros_async.errors import ConfigError, WorkerError
from uniros_async.runtime import make_vec
from uniros_async.runtime.ray_backend import RayPlacement
from uniros_async.runtime.supervisor import worker_groups

CART = "CartPole-v1"


def _returns(envs_per_worker: int, n: int, steps: int) -> list[tuple[np.ndarray, np.ndarray]]:
    venv = make_vec([CART] * n, envs_per_worker=envs_per_worker)
    try:
        obs, _ = venv.reset(seed=7)
        out = [(obs.copy(), np.zeros(n))]
        rng = np.random.default_rng(0)
        for _ in range(steps):
            obs, rewards, *_ = venv.step(rng.integers(0, 2, n))
            out.append((obs.copy(), rewards.copy()))
        return out
    finally:
        venv.close()


def test_consecutive_envs_share_a_process_and_step_as_they_would_alone() -> None:
    venv = make_vec([CART] * 5, envs_per_worker=2)
    try:
        pids = list(venv.pids)
        assert pids[0] == pids[1] and pids[2] == pids[3] and len(set(pids)) == 3  # 2 + 2 + 1
        # each env has its own connection, listener and index
        uris = {w.transport.peer for w in venv._sup.workers}
        assert len(uris) == 5 and [w.group for w in venv._sup.workers][:2] == [(0, 1), (0, 1)]
    finally:
        venv.close()
    assert not any(pid_alive(p) for p in set(pids) if p is not None)
    # the same seeds and actions give the same returns as one process per env (autoresets included: 300 steps)
    grouped, alone = _returns(3, 4, 300), _returns(1, 4, 300)
    for (o1, r1), (o2, r2) in zip(grouped, alone, strict=True):
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_array_equal(r1, r2)


@pytest.mark.skipif(
    not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
    reason="needs CPU affinity and at least two CPUs (the CI machine has two)",
)
def test_crowded_envs_grouped_one_process_per_core_are_pinned_a_core_each(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("UNIROS_SHARED_CORES", "pin")
    cpus = sorted(os.sched_getaffinity(0))
    n = 2 * len(cpus)  # twice as many envs as cores, two per process: one process per core
    venv = make_vec([CART] * n, envs_per_worker=2)
    try:
        procs = list(dict.fromkeys(venv.pids))
        assert len(procs) == len(cpus)
        pinned = [os.sched_getaffinity(p) for p in procs if p is not None]
        assert sorted(min(c) for c in pinned) == cpus and all(len(c) == 1 for c in pinned)
        assert all(w.info["cores_shared"] for w in venv._sup.workers)
        venv.reset(seed=0)
        obs, rewards, *_ = venv.step(np.zeros(n, np.int64))
        assert obs.shape == (n, 4) and (rewards == 1.0).all()
    finally:
        venv.close()


def test_a_killed_process_is_restarted_with_all_its_envs_truncated_and_the_others_untouched() -> None:
    venv = make_vec([CART] * 4, envs_per_worker=2, restart_on_failure=True)
    try:
        venv.reset(seed=0)
        old = venv.pids[2]
        assert old is not None and venv.pids[3] == old
        os.kill(old, signal.SIGKILL)
        restarted = None
        for _ in range(5):  # the kill may land just after a reply was sent
            step = venv.step(np.zeros(4, np.int64))
            if step[4].get("_worker_restarted", np.zeros(4, bool)).any():
                restarted = step
                break
        assert restarted is not None, "the dead process was not restarted"
        _, rewards, terminated, truncated, info = restarted
        assert list(info["_worker_restarted"]) == [False, False, True, True]
        assert truncated[2] and truncated[3] and not terminated[2:].any() and (rewards[2:] == 0.0).all()
        assert "shared with env" in info["worker_error"][3] or "shared with env" in info["worker_error"][2]
        assert venv.restarts == [0, 0, 1, 1]
        assert venv.pids[2] == venv.pids[3] != old and not pid_alive(old)
        obs, rewards, *_ = venv.step(np.zeros(4, np.int64))  # all four usable again
        assert obs.shape == (4, 4) and np.isfinite(obs).all()
    finally:
        venv.close()
    assert not any(pid_alive(p) for p in set(venv.pids) if p is not None)


def test_a_killed_process_is_reported_by_the_index_of_one_of_its_envs() -> None:
    venv = make_vec([CART] * 4, envs_per_worker=2)
    try:
        venv.reset(seed=0)
        victim = venv.pids[0]
        assert victim is not None
        os.kill(victim, signal.SIGKILL)
        with pytest.raises(WorkerError) as err:
            for _ in range(5):
                venv.step(np.zeros(4, np.int64))
        assert err.value.index in (0, 1)
        assert "died" in str(err.value) or "broke" in str(err.value)
    finally:
        venv.close()
    assert not any(pid_alive(p) for p in set(venv.pids) if p is not None)


@pytest.mark.parametrize("bad", [0, -1, True, "2", 1.5, "cores"])
def test_a_bad_envs_per_worker_is_refused_by_name_before_any_process_starts(bad: object) -> None:
    from uniros_async.runtime.launch import live_workers

    before = {p.pid for p in live_workers()}
    with pytest.raises(ConfigError, match=r"envs_per_worker must be an int >= 1 or 'auto', got"):
        make_vec([CART] * 2, envs_per_worker=bad)  # type: ignore[arg-type]
    assert {p.pid for p in live_workers()} <= before


def test_worker_groups_are_runs_of_the_same_placement_cut_at_the_count() -> None:
    arm = RayPlacement(resources={"rx200_arm": 1})
    arm_again = RayPlacement(resources={"rx200_arm": 1})  # equal, another object: grouped
    other = RayPlacement(resources={"ned2_arm": 1})
    placements = [None, None, None, arm, arm_again, other, None]
    assert worker_groups(placements, 1) == [[i] for i in range(7)]
    assert worker_groups(placements, 2) == [[0, 1], [2], [3, 4], [5], [6]]
    assert worker_groups(placements, 8) == [[0, 1, 2], [3, 4], [5], [6]]
    alone = [False, True, False, False, False, False, False]  # a spec marked alone is hosted by itself
    assert worker_groups(placements, 8, alone) == [[0], [1], [2], [3, 4], [5], [6]]


def test_auto_hosts_a_real_time_env_alone_and_the_accelerated_ones_one_process_per_core() -> None:
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    venv = make_vec(["uniros/Rx200Reach-v0"] + [("uniros/Rx200Reach-v0", {"clock": "sim"})] * (2 * cores))
    try:
        pids = list(venv.pids)
        assert pids[0] not in pids[1:]  # the wall-clock env has a process of its own
        assert len(set(pids[1:])) == cores  # the 2 * cores accelerated ones: two to a process, one per core
        obs, _ = venv.reset(seed=0)
        assert obs.shape == (1 + 2 * cores, 28)
    finally:
        venv.close()
    assert not any(pid_alive(p) for p in set(pids) if p is not None)


def test_a_real_time_env_in_a_shared_process_is_refused_with_what_to_do() -> None:
    from uniros_async.runtime.launch import live_workers

    with pytest.raises(WorkerError, match=r"runs on the wall clock .* make_vec\(envs_per_worker=1\)"):
        make_vec(["uniros/Rx200Reach-v0"] * 2, envs_per_worker=2, clock="wall")
    assert live_workers() == []  # the process is stopped


def _slow_to_build(delay_s: float) -> object:
    import time

    import gymnasium as gym

    time.sleep(delay_s)  # holds the worker's event loop, as an import of torch under load does
    return gym.make(CART)


def test_an_env_slow_to_build_does_not_cost_its_process_mates_their_connections() -> None:
    """Every env of a process is accepted before any is built: a build that holds the loop past the listeners'
    handshake deadline (``connect_timeout_s``, 5 s) no longer drops a mate's handshake mid-way."""
    import functools

    venv = make_vec([functools.partial(_slow_to_build, 6.0), functools.partial(_slow_to_build, 0.0)], envs_per_worker=2)
    try:
        assert venv.pids[0] == venv.pids[1]
        obs, _ = venv.reset(seed=0)
        assert obs.shape == (2, 4)
    finally:
        venv.close()
