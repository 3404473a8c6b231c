"""DelayAwareObservation on a real env (the rx200 reach on the accelerated sim, real MuJoCo)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from uniros_async.envs.delay_aware import DelayAwareObservation
from uniros_async.errors import ConfigError

KWARGS = {"reward_type": "dense", "action_mode": "delta", "robot": "sim", "clock": "sim"}


@pytest.mark.slow
def test_last_actions_newest_first_and_the_age() -> None:
    base = gym.make("uniros/Rx200Reach-v0", **KWARGS, imperfections={"latency": 2.0})
    env = DelayAwareObservation(base, action_history=2, observation_age=True)
    try:
        n_obs, n_act = base.observation_space.shape[0], base.action_space.shape[0]
        assert env.observation_space.shape == (n_obs + 2 * n_act + 1,)
        obs, info = env.reset(seed=0)
        assert np.array_equal(obs[n_obs:], np.zeros(2 * n_act + 1)) and info["observation_age_s"] == 0.0
        a1, a2 = np.full(n_act, 0.25, np.float32), np.full(n_act, -0.5, np.float32)
        env.step(a1)
        obs, _, _, _, info = env.step(a2)
        assert np.array_equal(obs[n_obs : n_obs + n_act], a2)  # newest first
        assert np.array_equal(obs[n_obs + n_act : n_obs + 2 * n_act], a1)
        assert obs[-1] == pytest.approx(info["observation_age_s"]) and 0.0 <= obs[-1] < 1.0
        assert env.observation_space.contains(obs)
        obs, _ = env.reset(seed=1)
        assert not obs[n_obs:].any()  # the history starts over
    finally:
        env.close()


def test_bad_settings_are_named() -> None:
    base = gym.make("uniros/Rx200Reach-v0", **KWARGS)
    try:
        with pytest.raises(ConfigError, match=r"action_history: expected an int >= 0, got -1"):
            DelayAwareObservation(base, action_history=-1)
        with pytest.raises(ConfigError, match="expected action_history >= 1 or observation_age=True"):
            DelayAwareObservation(base, action_history=0, observation_age=False)
    finally:
        base.close()


def test_goal_env_grows_only_its_observation_key() -> None:
    base = gym.make("uniros/Rx200ReachGoal-v0", reward_type="sparse", action_mode="delta", robot="sim", clock="sim")
    env = DelayAwareObservation(base, action_history=1, observation_age=False)
    try:
        n_act = base.action_space.shape[0]
        obs, _ = env.reset(seed=0)
        a = np.full(n_act, 0.1, np.float32)
        obs, reward, _, _, info = env.step(a)
        assert obs["observation"].shape == (base.observation_space["observation"].shape[0] + n_act,)
        assert np.array_equal(obs["observation"][-n_act:], a)
        assert reward == base.unwrapped.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)
    finally:
        env.close()
