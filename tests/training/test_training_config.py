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
    ("data", "message"),
    [
        ({"envs": [RX], "td3": {"batch_size": 128.5}}, "td3.batch_size: expected an integer, got 128.5"),
        ({"envs": [RX], "td3": {"batch_size": True}}, "td3.batch_size: expected an integer, got True"),
        ({"envs": [RX], "total_steps": "1e4.5"}, "total_steps: expected an integer, got '1e4.5'"),
        ({"envs": [RX], "total_steps": "1.5"}, "total_steps: expected an integer, got '1.5'"),
        ({"envs": [RX], "eval": {"episodes": 0}}, "eval.episodes: must be >= 1, got 0"),
        ({"envs": [RX], "eval": {"episodes": "many"}}, "eval.episodes: expected an integer, got 'many'"),
        ({"envs": [RX], "td3": {"tau": 2}}, "td3.tau: must be <= 1, got 2"),
        (
            {"envs": [RX], "td3": {"batch_size": 512, "buffer_size": 100}},
            "td3.batch_size: must be <= buffer_size (100), got 512",
        ),
        ({"envs": [RX], "td3": {"learning_rate": "fast"}}, "td3.learning_rate: expected a number, got 'fast'"),
        (
            {"envs": [RX], "td3": {"learning_rate": float("nan")}},
            "td3.learning_rate: expected a number (not NaN), got nan",
        ),
        ({"envs": [RX], "td3": {"net_arch": []}}, "td3.net_arch: expected at least 1 item(s), got []"),
        ({"envs": [RX], "td3": {"net_arch": [64, 0]}}, "td3.net_arch[1]: must be > 0, got 0"),
        ({"envs": [RX], "td3": {"net_arch": 64}}, "td3.net_arch: expected a list, got 64"),
        ({"envs": [RX], "td3": 5}, "td3: expected a mapping, got 5"),
        ({"envs": [RX], "learner": "turbo"}, "learner: expected one of 'sync', 'async', got 'turbo'"),
        (
            {"envs": [RX], "learner": "asinc"},
            "learner: expected one of 'sync', 'async', got 'asinc'; did you mean 'async'?",
        ),
        ({"envs": [RX], "total_steps": 0}, "total_steps: must be >= 1, got 0"),
        ({"envs": [RX], "normalize_obs": 1}, "normalize_obs: expected true or false, got 1"),
        ({"envs": [RX], "name": 5}, "name: expected a string, got 5"),
        ({"envs": [RX], "name": "a b"}, "name: must match ^[A-Za-z0-9_.+-]+$, got 'a b'"),
        (
            {"envs": [RX], "her": {"goal_selection_strategy": "past"}},
            "her.goal_selection_strategy: expected one of 'future', 'final', 'episode', got 'past'",
        ),
        ({"envs": []}, "envs: at least one env is needed, e.g. envs: [{id: uniros/Rx200Reach-v0}]"),
        ({}, "envs: at least one env is needed, e.g. envs: [{id: uniros/Rx200Reach-v0}]"),
        (
            {"envs": [RX, RX]},
            "envs: env labels must be unique (give envs a name:), got ['Rx200Reach', 'Rx200Reach']",
        ),
        ({"envs": [RX], "task_id_in_obs": True}, "task_id_in_obs: needs two or more envs"),
        (
            {"envs": "uniros/Rx200Reach-v0"},
            "envs: expected a list of envs (ids or {id, kwargs, name} mappings), got 'uniros/Rx200Reach-v0'",
        ),
        ({"envs": [RX, 5]}, "envs[1]: expected a mapping, got 5"),
        ({"envs": [RX, {"id": ""}]}, "envs[1].id: expected a non-empty string, got ''"),
        ({"envs": [RX, {"kwargs": {}}]}, "envs[1].id: missing (required)"),
        (
            {"envs": [RX], "eval": {"envs": [RX, {"id": "x", "kwargs": 3}]}},
            "eval.envs[1].kwargs: expected a mapping, got 3",
        ),
        ({"envs": [RX], "drop_observation": [3, 3]}, "drop_observation: must be distinct indices, got [3, 3]"),
        ({"envs": [RX], "drop_observation": [-1]}, "drop_observation[0]: must be >= 0, got -1"),
        ({"envs": [RX], "env_defaults": [1]}, "env_defaults: expected a mapping, got [1]"),
    ],
)
def test_bad_value_names_its_key_path(data: dict, message: str) -> None:
    with pytest.raises(ConfigError) as e:
        train_config_from_dict(data)
    assert str(e.value) == message


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (
            {"envs": [RX], "bogus": 1},
            "bogus: unknown key (valid keys: name, seed, total_steps, envs, env_defaults, randomize, placement, "
            "learner, "
            "concurrent, replay_buffer, task_id_in_obs, drop_observation, normalize_obs, td3, her, async_learner, "
            "eval, checkpoint, max_wall_s, torch_threads, run_dir, progress_bar, record, delay_aware)",
        ),
        ({"envs": [RX], "total_step": 1}, "total_step: unknown key; did you mean 'total_steps'?"),
        ({"envs": [RX], "td3": {"lr": 1}}, "td3.lr: unknown key; did you mean 'learning_rate'?"),
        ({"envs": [RX], "td3": {"batchsize": 1}}, "td3.batchsize: unknown key; did you mean 'batch_size'?"),
        ({"envs": [RX], "eval": {"episode": 1}}, "eval.episode: unknown key; did you mean 'episodes'?"),
        ({"envs": [{"id": RX["id"], "kwarg": {}}]}, "envs[0].kwarg: unknown key; did you mean 'kwargs'?"),
        (
            {"envs": [RX], "eval": {"envs": [RX, {"id": RX["id"], "nmae": "x"}]}},
            "eval.envs[1].nmae: unknown key; did you mean 'name'?",
        ),
    ],
)
def test_unknown_key_names_the_closest_valid_one(data: dict, message: str) -> None:
    with pytest.raises(ConfigError) as e:
        train_config_from_dict(data)
    assert str(e.value) == message


def test_every_problem_is_reported_on_its_own_line(tmp_path: Path) -> None:
    p = tmp_path / "c.yaml"
    p.write_text("envs: [uniros/Rx200Reach-v0]\ntd3: {batch_size: 128.5, tau: 0}\neval: {episodes: true}\n")
    with pytest.raises(ConfigError) as e:
        load_train_config(p)
    assert str(e.value).splitlines() == [
        f"{p}: 3 problems:",
        "  td3.batch_size: expected an integer, got 128.5",
        "  td3.tau: must be > 0, got 0",
        "  eval.episodes: expected an integer, got True",
    ]
    assert e.value.problems == [  # type: ignore[attr-defined]
        ("td3.batch_size", "expected an integer, got 128.5"),
        ("td3.tau", "must be > 0, got 0"),
        ("eval.episodes", "expected an integer, got True"),
    ]


def test_numbers_in_exponent_and_underscore_notation_work_everywhere(tmp_path: Path) -> None:
    # PyYAML (YAML 1.1) reads 3e-4 and 1e4 as strings; load_yaml reads them as numbers, and quoted ones work too
    p = tmp_path / "c.yaml"
    p.write_text(
        "total_steps: 1e4\nenvs: [uniros/Rx200Reach-v0]\n"
        "td3: {learning_rate: 3e-4, buffer_size: 1_000_000, batch_size: '2.56e2', tau: '5e-3', learning_starts: 1E3}\n"
        "eval: {every_steps: '1_000', episodes: 2.0}\n"
    )
    cfg = load_train_config(p)
    assert cfg.total_steps == 10_000 and isinstance(cfg.total_steps, int)
    t = cfg.td3
    assert (t.learning_rate, t.buffer_size, t.batch_size, t.tau, t.learning_starts) == (
        3e-4,
        1_000_000,
        256,
        5e-3,
        1000,
    )
    assert all(isinstance(v, int) for v in (t.buffer_size, t.batch_size, t.learning_starts, cfg.eval.every_steps))
    assert (cfg.eval.every_steps, cfg.eval.episodes) == (1000, 2)
    assert train_config_from_dict({"envs": [RX], "total_steps": "1e4"}).total_steps == 10_000


def test_configs_are_frozen() -> None:
    cfg = train_config_from_dict({"envs": [RX]})
    with pytest.raises(ValueError, match="frozen"):
        cfg.td3.batch_size = 1  # type: ignore[misc]
    with pytest.raises(ValueError, match="frozen"):
        cfg.total_steps = 1  # type: ignore[misc]


def test_unknown_env_id_and_kwargs_are_found_before_anything_starts() -> None:
    cfg = train_config_from_dict({"envs": [{"id": "uniros/Nope-v0"}]})
    with pytest.raises(ConfigError, match=r"^envs\[0\]: unknown env id 'uniros/Nope-v0'"):
        cfg.check_envs()
    cfg = train_config_from_dict({"envs": [{"id": "uniros/Rx200Reach-v0", "kwargs": {"reward": "dense"}}]})
    with pytest.raises(
        ConfigError, match=r"^envs\[0\]\.kwargs\.reward: unknown keyword argument; did you mean 'reward_type'"
    ):
        cfg.check_envs()
    cfg = train_config_from_dict({"envs": [{"id": "uniros/Rx200Reach-v0", "kwargs": {"action_cycle_s": -1}}]})
    with pytest.raises(ConfigError, match=r"^envs\[0\]\.kwargs\.action_cycle_s: must be > 0, got -1$"):
        cfg.check_envs()


def test_env_kwargs_errors_carry_their_path_in_the_config() -> None:
    ned = {"id": "uniros/Ned2Reach-v0", "kwargs": {"reward_type": "spars", "action_cycle_s": True}}
    data = {
        "envs": [RX, ned],
        "env_defaults": {"clock": "sim", "unsafe_action": "clip"},
        "eval": {"envs": [{"id": "uniros/Rx200ReachGoal-v0", "kwargs": {"goal_min": [0.1, 0.2]}}]},
    }
    with pytest.raises(ConfigError) as e:
        train_config_from_dict(data).check_envs()
    lines = str(e.value).splitlines()
    assert lines[0] == "4 problems:"
    assert sorted(line.strip() for line in lines[1:]) == [
        "env_defaults.unsafe_action: expected one of 'hold', 'project', got 'clip'",  # once, not once per env
        "envs[1].kwargs.action_cycle_s: expected a number, got True",
        "envs[1].kwargs.reward_type: expected one of 'dense', 'sparse', got 'spars'; did you mean 'sparse'?",
        "eval.envs[0].kwargs.goal_min: expected 3 numbers [x, y, z], got [0.1, 0.2]",
    ]


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


PIXEL_CONFIGS = sorted(CONFIGS.glob("*_pixels_drq*.yaml"))
"""The pixel recipe's configs (``python -m uniros_async.training.pixel_train``), checked by its own loader."""


@pytest.mark.parametrize("path", sorted(set(CONFIGS.glob("*.yaml")) - set(PIXEL_CONFIGS)), ids=lambda p: p.name)
def test_shipped_configs_load_and_check(path: Path) -> None:
    cfg = load_train_config(path)
    assert isinstance(cfg, TrainConfig)
    cfg.check_envs()


@pytest.mark.parametrize("path", PIXEL_CONFIGS, ids=lambda p: p.name)
def test_shipped_pixel_configs_load(path: Path) -> None:
    from uniros_async.config import load_config
    from uniros_async.training.pixel_train import PixelTrainConfig

    cfg = load_config(path, PixelTrainConfig)
    assert cfg.total_steps > 0 and cfg.env_id.startswith("uniros/")


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
    from uniros_async.training.build import EnvLayout, model_kwargs

    data: dict = {"envs": [RX], "learner": "async", "env_defaults": env_defaults}
    if setting is not None:
        data["async_learner"] = {"real_time_actor": setting}
    cfg = train_config_from_dict(data)
    layout = EnvLayout(pad_to=None, task_id_size=0, goal_env=False, obs_size=20, action_size=5, labels=("Rx200Reach",))
    assert model_kwargs(cfg, layout, tmp_path)["real_time_actor"] is expected


def test_action_l2_needs_the_async_learner() -> None:
    with pytest.raises(ConfigError, match=r"async_learner.action_l2=1.0 needs learner: async"):
        train_config_from_dict({"envs": [RX], "async_learner": {"action_l2": 1.0}})
    with pytest.raises(ConfigError, match=r"^async_learner.action_l2: must be >= 0, got -1$"):
        train_config_from_dict({"envs": [RX], "learner": "async", "async_learner": {"action_l2": -1}})
    cfg = train_config_from_dict({"envs": [RX], "learner": "async", "async_learner": {"action_l2": 1.0}})
    assert cfg.async_learner.action_l2 == 1.0


def test_delay_aware_wraps_every_env_and_refuses_what_it_cannot_do() -> None:
    import numpy as np

    from uniros_async.training.build import build_eval_envs, build_train_env

    cfg = train_config_from_dict({"envs": [RX], "delay_aware": {"action_history": 2}})
    assert cfg.delay_aware_args() == (2, True)
    sampler, layout = build_train_env(cfg)
    evals = build_eval_envs(cfg, layout)
    try:
        # the reach observation, then the last two actions, then the age: training and evaluation envs alike
        n_obs, n_act = 28, layout.action_size
        assert layout.obs_size == n_obs + 2 * n_act + 1
        assert [e.observation_space.shape for _, _, e in evals] == [(layout.obs_size,)]
        sampler.reset(seed=0)
        action = np.full(n_act, 0.5, dtype=np.float32)
        obs, *_ = sampler.step(action)
        history = obs[n_obs : n_obs + 2 * n_act]
        assert np.allclose(history[:n_act], action) and np.allclose(history[n_act:], 0.0)  # newest first, then zeros
        assert obs[-1] >= 0.0
    finally:
        sampler.close()
        for _, _, e in evals:
            e.close()
    with pytest.raises(ConfigError, match="delay_aware: wraps each env of a run, and a concurrent run steps a vector"):
        train_config_from_dict(
            {"envs": [RX], "placement": "workers", "concurrent": True, "delay_aware": {"observation_age": False}}
        )
    with pytest.raises(ConfigError, match="delay_aware.observation_age: reads the env.s own timing.*workers"):
        train_config_from_dict({"envs": [RX], "placement": "workers", "delay_aware": {}})
    with pytest.raises(ConfigError, match="delay_aware: adds nothing"):
        train_config_from_dict({"envs": [RX], "delay_aware": {"action_history": 0, "observation_age": False}})
    assert train_config_from_dict({"envs": [RX]}).delay_aware_args() is None
