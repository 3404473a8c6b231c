"""LocalGoalReward: HER's relabelled rewards computed in the agent's process equal the env's own, and never ask it."""

from __future__ import annotations

import copy
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import HerReplayBuffer
from stable_baselines3.common.vec_env import DummyVecEnv

import uniros_async
from uniros_async.errors import ConfigError
from uniros_async.tasks.reach import reach_reward
from uniros_async.training.her import LocalGoalReward, computes_reward_locally

pytestmark = pytest.mark.slow

RX_GOAL, NED_GOAL = "uniros/Rx200ReachGoal-v0", "uniros/Ned2ReachGoal-v0"


def _relabelled(achieved: np.ndarray, desired: np.ndarray, infos: list[dict[str, Any]], seed: int) -> tuple[Any, ...]:
    """HER-style queries from real transitions: the real goals, goals of other transitions, and the achieved goals
    themselves (reached), with the real infos and the same infos with both penalties set."""
    rng = np.random.default_rng(seed)
    goals = np.concatenate([desired, desired[rng.permutation(len(desired))], achieved])
    ach = np.concatenate([achieved] * 3)
    info = np.array(infos * 3, dtype=object)
    flagged = np.array([{**i, "joint_limit_hit": True, "not_executable": True} for i in infos * 3], dtype=object)
    return ach, goals, info, flagged


def _rollout(step: Any, n: int) -> tuple[np.ndarray, np.ndarray, list[dict[str, Any]]]:
    ach, des, infos = [], [], []
    for _ in range(n):
        obs, info = step()
        ach.append(obs["achieved_goal"])
        des.append(obs["desired_goal"])
        infos.append({k: info[k] for k in ("joint_limit_hit", "not_executable", "is_success", "distance")})
    return np.asarray(ach), np.asarray(des), infos


def test_reach_reward_is_batch_reward() -> None:
    env = gym.make(RX_GOAL, clock="sim", reward_type="dense", reach_tolerance=0.05)
    try:
        env.reset(seed=1)
        raw = env.unwrapped

        def step() -> tuple[Any, dict[str, Any]]:
            obs, _, terminated, truncated, info = env.step(env.action_space.sample())
            if terminated or truncated:
                env.reset()
            return obs, info

        ach, goals, info, flagged = _relabelled(*_rollout(step, 30), seed=0)
        for infos in (info, flagged, info[0], {}):
            got = reach_reward(ach, goals, infos, reward_type="dense", reach_tolerance=0.05)
            np.testing.assert_array_equal(got, raw.compute_reward(ach, goals, infos))
        assert np.any(got == 20.0) and np.any(got < 0)  # both branches seen (the achieved goals are reached)
        flagged_r = reach_reward(ach, goals, flagged, reward_type="dense", reach_tolerance=0.05)
        plain_r = reach_reward(ach, goals, {}, reward_type="dense", reach_tolerance=0.05)
        np.testing.assert_allclose(flagged_r, plain_r - 7.0)
        with pytest.raises(ConfigError, match="reward_type must be one of"):
            reach_reward(ach, goals, {}, reward_type="shaped", reach_tolerance=0.05)
    finally:
        env.close()


def test_local_rewards_equal_the_envs_own_in_process_and_in_workers() -> None:
    specs = [(RX_GOAL, {"reward_type": "dense", "reach_tolerance": 0.05}), (NED_GOAL, {"reward_type": "sparse"})]
    venv = uniros_async.make_vec(specs, clock="sim").as_sb3()  # padded: rx200 and ned2
    local_env = gym.make(RX_GOAL, clock="sim", reward_type="sparse", reach_tolerance=0.03)
    try:
        local = LocalGoalReward(venv)
        assert local.settings == [
            {"reward_type": "dense", "reach_tolerance": 0.05},
            {"reward_type": "sparse", "reach_tolerance": 0.02},
        ]
        venv.reset()

        def step() -> tuple[Any, dict[str, Any]]:
            obs, _, _, infos = venv.step(np.stack([venv.action_space.sample() for _ in range(2)]))
            return {k: v[0] for k, v in obs.items()}, infos[0]  # rx200's transition

        ach, goals, info, flagged = _relabelled(*_rollout(step, 30), seed=1)
        for infos in (info, flagged):
            for i in (0, 1):
                want = venv.env_method("compute_reward", ach, goals, infos, indices=[i])  # in the worker
                got = local.env_method("compute_reward", ach, goals, infos, indices=[i])
                assert len(got) == 1
                np.testing.assert_array_equal(got[0], want[0])
        assert np.any(got[0] == 1.0) and np.any(got[0] == -1.0)
        local.set_attr("reach_tolerance", 0.5, indices=[1])  # a setting changed through the wrapper follows
        np.testing.assert_array_equal(
            local.env_method("compute_reward", ach, goals, info, indices=[1])[0],
            venv.env_method("compute_reward", ach, goals, info, indices=[1])[0],
        )
        # everything else is forwarded
        assert local.get_attr("reward_type") == ["dense", "sparse"]
        assert local.env_method("compute_terminated", ach[:3], ach[:3], {}, indices=[1])[0].tolist() == [True] * 3

        dummy = LocalGoalReward(DummyVecEnv([lambda: local_env]))
        local_env.reset(seed=2)

        def local_step() -> tuple[Any, dict[str, Any]]:
            obs, _, terminated, truncated, info = local_env.step(local_env.action_space.sample())
            if terminated or truncated:
                local_env.reset()
            return obs, info

        ach, goals, info, _ = _relabelled(*_rollout(local_step, 20), seed=2)
        want = local_env.unwrapped.compute_reward(ach, goals, info)
        np.testing.assert_array_equal(dummy.env_method("compute_reward", ach, goals, info, indices=[0])[0], want)
    finally:
        venv.close()
        local_env.close()


def test_her_sampling_over_workers_never_calls_a_worker() -> None:
    venv = uniros_async.make_vec([(RX_GOAL, {"max_episode_steps": 8})] * 2, clock="sim").as_sb3()
    try:
        local = LocalGoalReward(venv)
        assert computes_reward_locally(local) and not computes_reward_locally(venv)
        buffer = HerReplayBuffer(
            1_000,
            venv.observation_space,
            venv.action_space,
            env=local,
            n_envs=2,
            n_sampled_goal=4,
            goal_selection_strategy="future",
        )
        obs = venv.reset()
        for _ in range(20):
            actions = np.stack([venv.action_space.sample() for _ in range(2)])
            new_obs, rewards, dones, infos = venv.step(actions)
            next_obs = copy.deepcopy(new_obs)
            for i, done in enumerate(dones):
                if done:
                    for k in next_obs:
                        next_obs[k][i] = infos[i]["terminal_observation"][k]
            buffer.add(obs, next_obs, actions, rewards, dones, infos)
            obs = new_obs

        calls: list[str] = []
        inner_env_method = venv.env_method

        def counting(name: str, *args: Any, **kwargs: Any) -> list[Any]:
            calls.append(name)
            return inner_env_method(name, *args, **kwargs)

        venv.env_method = counting  # type: ignore[method-assign]
        batches = [buffer.sample(64) for _ in range(20)]
        assert calls == []
        # the relabelled rewards (the batch's last her_ratio part) are what the worker says for the same queries
        venv.env_method = inner_env_method  # type: ignore[method-assign]
        n_virtual = int(buffer.her_ratio * 64)
        for b in batches[:3]:
            ach = b.next_observations["achieved_goal"].numpy()[-n_virtual:]
            des = b.observations["desired_goal"].numpy()[-n_virtual:]
            want = venv.env_method("compute_reward", ach, des, [{}] * n_virtual, indices=[0])[0]
            np.testing.assert_array_equal(b.rewards.numpy().ravel()[-n_virtual:], want.astype(np.float32))
    finally:
        venv.close()


def test_an_env_without_the_settings_is_a_clear_error() -> None:
    venv = DummyVecEnv([lambda: gym.make("Pendulum-v1")])
    try:
        with pytest.raises(ConfigError, match="needs the env attribute 'reward_type'.*reward_fn="):
            LocalGoalReward(venv)
        assert computes_reward_locally(venv)
        custom = LocalGoalReward(venv, reward_fn=lambda a, d, i, *, scale: -scale * np.ones(len(a)), settings=())
        assert custom.env_method("compute_reward", np.zeros((2, 3)), np.zeros((2, 3)), {}, scale=2.0)[0].tolist() == [
            -2.0,
            -2.0,
        ]
    finally:
        venv.close()


def test_a_worker_proxy_inside_dummy_vec_env_is_not_local() -> None:
    proxy = uniros_async.make(RX_GOAL, clock="sim")
    venv = DummyVecEnv([lambda: proxy])
    try:
        assert not computes_reward_locally(venv)  # its compute_reward would be a round trip to the worker
        with pytest.raises(ConfigError, match="reward_type"):  # and the proxy does not expose the settings
            LocalGoalReward(venv)
    finally:
        venv.close()
