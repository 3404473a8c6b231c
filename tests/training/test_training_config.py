"""TrainConfig: the paper's defaults, YAML loading, and bad input rejected before anything starts."""

from __future__ import annotations

from pathlib import Path

import pytest

from uniros_async.errors import ConfigError
from uniros_async.training.config import (
    EnvEntry,
    TrainConfig,
    config_to_dict,
    load_train_config,
    train_config_from_dict,
)

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
RX = {"id": "uniros/Rx200Reach-v0"}


def test_defaults_are_the_papers() -> None:
    cfg = train_config_from_dict({"envs": [RX]})
    t = cfg.td3
    assert (t.learning_rate, t.buffer_size, t.batch_size, t.tau, t.gamma) == (3e-4, 1_000_000, 256, 0.005, 0.99)
    assert t.net_arch == (400, 300) and t.policy_delay == 2
    assert (t.target_policy_noise, t.target_noise_clip) == (0.2, 0.5)
    assert (cfg.her.n_sampled_goal, cfg.her.goal_selection_strategy) == (4, "future")
    assert cfg.torch_threads == 1 and cfg.learner == "sync" and cfg.env_defaults == {"clock": "sim"}
    assert cfg.env_specs() == [("Rx200Reach", "uniros/Rx200Reach-v0", {"clock": "sim"})]


def test_env_entries_labels_and_overrides(tmp_path: Path) -> None:
    p = tmp_path / "c.yaml"
    p.write_text(
        "name: mt\nenvs:\n  - uniros/Rx200Reach-v0\n  - {id: uniros/Ned2Reach-v0, kwargs: {robot: emulated-real}}\n"
        "td3: {learning_rate: 1e-3}\n"  # YAML 1.1 reads 1e-3 as a string: accepted as the number
    )
    cfg = load_train_config(p, {"td3.batch_size": 64, "eval.episodes": 3})
    assert cfg.labels() == ["Rx200Reach", "Ned2Reach-emulated-real"]
    assert cfg.td3.learning_rate == 1e-3 and cfg.td3.batch_size == 64 and cfg.eval.episodes == 3
    assert isinstance(cfg.envs[0], EnvEntry)
    again = train_config_from_dict(config_to_dict(cfg))
    assert again == cfg


@pytest.mark.parametrize(
    ("data", "match"),
    [
        ({"envs": [RX], "bogus": 1}, r"unknown key\(s\) \['bogus'\]; valid keys are \[.*'total_steps'"),
        ({"envs": [RX], "td3": {"lr": 1}}, r"td3: unknown key\(s\) \['lr'\].*'learning_rate'"),
        ({"envs": [{"id": "uniros/Rx200Reach-v0", "kwarg": {}}]}, r"envs\[0\]: unknown key\(s\) \['kwarg'\]"),
        ({"envs": []}, "at least one env"),
        ({"envs": [RX], "td3": {"tau": 2}}, r"tau must be in \(0, 1\]"),
        ({"envs": [RX], "td3": {"batch_size": 512, "buffer_size": 100}}, "batch_size=512 > td3.buffer_size=100"),
        ({"envs": [RX], "td3": {"learning_rate": "fast"}}, "expected a number, got 'fast'"),
        ({"envs": [RX], "td3": {"net_arch": []}}, "net_arch"),
        ({"envs": [RX], "learner": "turbo"}, "learner must be one of"),
        ({"envs": [RX], "total_steps": 0}, "total_steps must be >= 1"),
        ({"envs": [RX], "her": {"goal_selection_strategy": "past"}}, "goal_selection_strategy"),
        ({"envs": [RX, RX]}, "labels must be unique"),
        ({"envs": [RX], "task_id_in_obs": True}, "two or more envs"),
        ({"envs": "uniros/Rx200Reach-v0"}, "expected a list of envs"),
        ({"envs": [RX], "drop_observation": [3, 3]}, "distinct indices"),
        ({"envs": [RX], "drop_observation": [-1]}, "distinct indices >= 0"),
    ],
)
def test_bad_config_is_a_clear_error(data: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        train_config_from_dict(data)


def test_unknown_env_id_and_kwargs_are_found_before_anything_starts() -> None:
    cfg = train_config_from_dict({"envs": [{"id": "uniros/Nope-v0"}]})
    with pytest.raises(ConfigError, match=r"envs\[0\] .*unknown env id 'uniros/Nope-v0'"):
        cfg.check_envs()
    cfg = train_config_from_dict({"envs": [{"id": "uniros/Rx200Reach-v0", "kwargs": {"reward": "dense"}}]})
    with pytest.raises(ConfigError, match=r"unknown keyword argument\(s\) \['reward'\]"):
        cfg.check_envs()
    cfg = train_config_from_dict({"envs": [{"id": "uniros/Rx200Reach-v0", "kwargs": {"action_cycle_s": -1}}]})
    with pytest.raises(ConfigError, match="action_cycle_s must be in"):
        cfg.check_envs()


def test_missing_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read config file"):
        load_train_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("envs: [\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_train_config(bad)
    listy = tmp_path / "list.yaml"
    listy.write_text("- 1\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_train_config(listy)


@pytest.mark.parametrize("path", sorted(CONFIGS.glob("*.yaml")), ids=lambda p: p.name)
def test_shipped_configs_load_and_check(path: Path) -> None:
    cfg = load_train_config(path)
    assert isinstance(cfg, TrainConfig)
    cfg.check_envs()


def test_drop_observation_removes_entries() -> None:
    import gymnasium as gym
    import numpy as np

    from uniros_async.training.multitask import DropObservation

    env = gym.make("uniros/Rx200ReachGoal-v0", clock="sim")  # its observation: 24 goal-independent entries
    try:
        full, _ = env.reset(seed=0)
        wrapped = DropObservation(env, (13, 14, 15))  # e.g. the previous action's last entries
        obs, _ = wrapped.reset(seed=0)
        assert wrapped.observation_space["observation"].shape == (21,)
        assert np.array_equal(obs["observation"], np.delete(full["observation"], [13, 14, 15]))
        assert np.array_equal(obs["desired_goal"], full["desired_goal"])
        with pytest.raises(ConfigError, match=r"drop_observation \[24\] outside the observation of size 24"):
            DropObservation(env, (24,))
    finally:
        env.close()


@pytest.mark.parametrize(
    ("env_defaults", "setting", "expected"),
    [
        ({"clock": "sim"}, None, False),  # accelerated training: the actor computes flat out
        ({"clock": "wall"}, None, True),  # real-time envs: a real-time acting thread
        ({}, None, True),  # an env's own default clock is the wall clock
        ({"turn_based": True}, None, False),  # ... and the sim clock when turn-based
        ({"clock": "wall"}, False, False),  # an explicit setting wins
        ({"clock": "sim"}, True, True),
    ],
)
def test_async_learner_real_time_actor_follows_the_envs_clock(
    env_defaults: dict, setting: bool | None, expected: bool, tmp_path: Path
) -> None:
    from uniros_async.training.recipes import EnvLayout, model_kwargs

    data: dict = {"envs": [RX], "learner": "async", "env_defaults": env_defaults}
    if setting is not None:
        data["async_learner"] = {"real_time_actor": setting}
    cfg = train_config_from_dict(data)
    layout = EnvLayout(pad_to=None, task_id_size=0, goal_env=False, obs_size=20, action_size=5, labels=("Rx200Reach",))
    assert model_kwargs(cfg, layout, tmp_path)["real_time_actor"] is expected


def test_action_l2_needs_the_async_learner() -> None:
    with pytest.raises(ConfigError, match=r"async_learner.action_l2=1.0 needs learner: async"):
        train_config_from_dict({"envs": [RX], "async_learner": {"action_l2": 1.0}})
    with pytest.raises(ConfigError, match=r"async_learner.action_l2 must be >= 0, got -1"):
        train_config_from_dict({"envs": [RX], "learner": "async", "async_learner": {"action_l2": -1}})
    cfg = train_config_from_dict({"envs": [RX], "learner": "async", "async_learner": {"action_l2": 1.0}})
    assert cfg.async_learner.action_l2 == 1.0
