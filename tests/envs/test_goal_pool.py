"""The reach task's goals come from a pool drawn at construction, so a reset runs no IK on the env loop's thread.

Real envs on the sim clock, in this process. ``sample_goal`` is wrapped on the instance to count its calls (a spy:
the draws still run).
"""

from __future__ import annotations

import threading
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from uniros_async.errors import ConfigError
from uniros_async.tasks.reach import GOAL_POOL_SEED


def _spy_on_draws(env: Any) -> list[str]:
    """Wrap ``env.sample_goal``: the name of the thread of each call is appended to the list returned."""
    calls: list[str] = []
    draw = env.sample_goal

    def counted(*args: Any, **kwargs: Any) -> np.ndarray:
        calls.append(threading.current_thread().name)
        return draw(*args, **kwargs)  # type: ignore[no-any-return]

    env.sample_goal = counted
    return calls


def test_a_reset_picks_from_the_pool_and_its_seed_decides_the_goal() -> None:
    envs = [gym.make("uniros/Rx200Reach-v0", clock="sim", goal_space="workspace", goal_pool=64) for _ in range(2)]
    try:
        a, b = (e.unwrapped for e in envs)
        assert a.goal_pool.shape == (64, 3)
        assert a.goal_pool is b.goal_pool  # one fixed seed: the same pool in every env, drawn once per process
        assert not a.goal_pool.flags.writeable
        for g in a.goal_pool[:8]:  # each reachable by a safe IK solution, inside the box
            assert np.all(g >= a.goal_min) and np.all(g <= a.goal_max)
            q, ok = a.kin.ik(g, rng=GOAL_POOL_SEED)
            assert ok and a.safety.check(q) is None
        calls = _spy_on_draws(a)
        goals = []
        for seed in (3, 4, 3):
            envs[0].reset(seed=seed)
            goals.append(a.goal.copy())
        assert calls == []  # no draw at reset: the pool's goals only
        assert any(np.array_equal(goals[0], g) for g in a.goal_pool)
        np.testing.assert_array_equal(goals[0], goals[2])  # the reset's seed decides
        envs[1].reset(seed=3)
        np.testing.assert_array_equal(b.goal, goals[0])  # in another env too
        picks = set()
        for _ in range(20):  # unseeded resets go on through the pool
            envs[0].reset()
            picks.add(a.goal.tobytes())
        assert len(picks) > 5
    finally:
        for e in envs:
            e.close()


def test_goal_pool_zero_draws_each_goal_at_reset() -> None:
    env = gym.make("uniros/Ned2Reach-v0", clock="sim", goal_pool=0)
    try:
        u = env.unwrapped
        assert u.goal_pool is None
        calls = _spy_on_draws(u)
        env.reset(seed=1)
        first = u.goal.copy()
        env.reset(seed=1)
        assert len(calls) == 2 and calls[0] != threading.current_thread().name  # drawn on the env loop's thread
        np.testing.assert_array_equal(u.goal, first)
    finally:
        env.close()


@pytest.mark.slow  # the unreachable box's 200 draws, each IK from every restart
def test_an_unreachable_box_and_a_negative_pool_are_clear_errors_at_construction() -> None:
    with pytest.raises(ConfigError, match=r"no reachable goal in the box \[2\.0, 2\.0, 2\.0\]"):
        gym.make("uniros/Rx200Reach-v0", clock="sim", goal_min=[2.0, 2.0, 2.0], goal_max=[2.1, 2.1, 2.1])
    with pytest.raises(ConfigError, match="goal_pool"):
        gym.make("uniros/Rx200Reach-v0", clock="sim", goal_pool=-1)
