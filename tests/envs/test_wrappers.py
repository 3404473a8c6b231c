"""Wrappers on real reach envs (accelerated sim clock)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import uniros_async  # noqa: F401
from uniros_async.envs.wrappers import NormalizeObservation, PadSpaces, TimeLimit
from uniros_async.errors import ConfigError

pytestmark = pytest.mark.slow


def test_padding_lets_both_arms_share_one_policy() -> None:
    rx = PadSpaces(gym.make("uniros/Rx200Reach-v0", clock="sim"), obs_size=32, action_size=6)
    ned = PadSpaces(gym.make("uniros/Ned2Reach-v0", clock="sim"), obs_size=32, action_size=6)
    try:
        assert rx.observation_space.shape == ned.observation_space.shape == (32,)
        assert rx.action_space.shape == ned.action_space.shape == (6,)
        obs, info = rx.reset(seed=0)
        assert obs.shape == (32,) and np.all(obs[28:] == 0) and info["padding"] == {"observation": 4, "action": 1}
        obs, _, _, _, info = rx.step(np.full(6, 0.1, np.float32))  # the 6th entry is ignored
        assert rx.observation_space.contains(obs) and info["padding"]["action"] == 1
        obs, info = ned.reset(seed=0)
        assert info["padding"] == {"observation": 7, "action": 0}
        with pytest.raises(gym.error.InvalidAction, match=r"\(6,\)"):
            ned.step(np.zeros(5, np.float32))
        with pytest.raises(ConfigError, match="cannot pad"):
            PadSpaces(rx.env, obs_size=10, action_size=6)
    finally:
        rx.close()
        ned.close()


def test_normalized_observation_within_bounds_goal_keys_untouched() -> None:
    env = NormalizeObservation(gym.make("uniros/Rx200ReachGoal-v0", clock="sim"))
    try:
        obs, _ = env.reset(seed=2)
        assert np.all(np.abs(obs["observation"]) <= 1.0)
        raw = env.unwrapped
        np.testing.assert_allclose(obs["desired_goal"], raw.goal.astype(np.float32))
        obs, reward, *_ = env.step(env.action_space.sample())
        assert reward == raw.compute_reward(obs["achieved_goal"], obs["desired_goal"], _[-1])
    finally:
        env.close()


def test_time_limit_marks_truncation_unsuccessful() -> None:
    env = TimeLimit(gym.make("uniros/Ned2Reach-v0", clock="sim").unwrapped, max_episode_steps=2)
    try:
        env.reset(seed=0)
        env.step(np.zeros(6, np.float32))
        _, _, terminated, truncated, info = env.step(np.zeros(6, np.float32))
        assert truncated and not terminated and info["is_success"] is False
    finally:
        env.close()
