"""``normalize_obs``: SB3 VecNormalize on the training env (observations only), its statistics saved with every
checkpoint, restored on resume, and used (frozen) by the periodic evaluation and by ``uniros eval``; the replay
buffer keeps raw observations. Short real runs in the accelerated sim clock (asserting the plumbing, not learning)."""

from __future__ import annotations

import pickle
import shutil
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from uniros_async.errors import ConfigError
from uniros_async.training import evaluate as evaluate_mod
from uniros_async.training import recipes, run_state
from uniros_async.training.checkpoint import CheckpointError, load_obs_stats, read_meta
from uniros_async.training.config import config_to_dict, train_config_from_dict
from uniros_async.training.evaluate import evaluate_checkpoint, load_policy

RX = "uniros/Rx200Reach-v0"
NED = "uniros/Ned2Reach-v0"
RX_GOAL = {"id": "uniros/Rx200ReachGoal-v0", "kwargs": {"reward_type": "sparse"}}
GOAL_KEYS = {"observation", "achieved_goal", "desired_goal"}


def _cfg(run_dir: Path, **over: Any) -> Any:
    """test_training_pipeline's small config (same directory), with normalisation and without periodic work."""
    from test_training_pipeline import _cfg as pipeline_cfg

    defaults = {"normalize_obs": True, "eval": {"every_steps": 0}, "checkpoint": {"every_steps": 0, "keep": 3}}
    return pipeline_cfg(run_dir, **{**defaults, **over})


# ---------------------------------------------------------------- config


def test_normalize_obs_is_off_by_default_and_must_be_a_bool() -> None:
    assert train_config_from_dict({"envs": [RX]}).normalize_obs is False
    cfg = train_config_from_dict({"envs": [RX], "normalize_obs": True})
    assert cfg.normalize_obs is True and train_config_from_dict(config_to_dict(cfg)) == cfg
    for bad in ("yes", 1, None, {"obs": True}):
        with pytest.raises(ConfigError, match=r"^normalize_obs: expected true or false, got"):
            train_config_from_dict({"envs": [RX], "normalize_obs": bad})


# ---------------------------------------------------------------- spies


class _LastObs(gym.Wrapper[Any, Any, Any, Any]):
    """Remembers the raw observation the env last returned (what the policy is about to be asked about)."""

    last: Any = None

    def reset(self, **kwargs: Any) -> Any:
        obs, info = self.env.reset(**kwargs)
        _LastObs.last = obs
        return obs, info

    def step(self, action: Any) -> Any:
        out = self.env.step(action)
        _LastObs.last = out[0]
        return out


def _spy_predict(monkeypatch: pytest.MonkeyPatch, cls: type, pairs: list[tuple[Any, Any]]) -> None:
    """Record (raw observation, observation given to predict) for every deterministic (evaluation) predict."""
    original = cls.predict

    def predict(self: Any, observation: Any, *args: Any, deterministic: bool = False, **kwargs: Any) -> Any:
        if deterministic:
            pairs.append((_LastObs.last, observation))
        return original(self, observation, *args, deterministic=deterministic, **kwargs)

    monkeypatch.setattr(cls, "predict", predict)


def _assert_normalised_with(pairs: list[tuple[Any, Any]], stats: Any) -> None:
    assert pairs
    for raw, seen in pairs:
        want = stats.normalize_obs(raw)
        for key in GOAL_KEYS:
            np.testing.assert_allclose(seen[key], want[key], rtol=1e-5, atol=1e-5)
        assert not np.allclose(seen["observation"], raw["observation"])


# ---------------------------------------------------------------- runs


@pytest.mark.slow
def test_her_run_saves_resumes_and_evaluates_with_the_obs_statistics(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from stable_baselines3 import TD3

    pairs: list[tuple[Any, Any]] = []
    eval_steps: list[tuple[int, int]] = []  # (step, index of its first pair)
    _spy_predict(monkeypatch, TD3, pairs)
    build_eval_envs, run_eval = recipes.build_eval_envs, run_state.run_eval

    def recorded_eval_envs(*a: Any, **k: Any) -> Any:
        return [(label, env_id, _LastObs(env)) for label, env_id, env in build_eval_envs(*a, **k)]

    def marked_run_eval(model: Any, step: int, *a: Any, **k: Any) -> Any:
        eval_steps.append((step, len(pairs)))
        return run_eval(model, step, *a, **k)

    monkeypatch.setattr(recipes, "build_eval_envs", recorded_eval_envs)
    monkeypatch.setattr(run_state, "run_eval", marked_run_eval)
    run = tmp_path / "her_norm"
    over = {
        "envs": [RX_GOAL],
        "td3": {"learning_starts": 100},
        "eval": {"every_steps": 100},
        "checkpoint": {"every_steps": 100},
    }
    result = recipes.train(_cfg(run, total_steps=200, **over))
    ckpts = run / "checkpoints"

    # every checkpoint holds the statistics; they grow with the steps
    s100, s200 = (load_obs_stats(ckpts / f"step_{n:09d}") for n in (100, 200))
    assert read_meta(result.checkpoint).normalize_obs and (result.checkpoint / "vec_normalize.pkl").is_file()
    assert set(s200.obs_rms) == GOAL_KEYS and not s200.training and not s200.norm_reward
    c100, c200 = s100.obs_rms["observation"].count, s200.obs_rms["observation"].count
    assert 100 < c100 < 110 and 99.5 < c200 - c100 < 110  # one per step (+ one per reset)
    rms = s200.obs_rms["observation"]
    assert np.any(np.abs(rms.mean) > 0.1) and np.all(rms.var >= 0)

    # the replay buffer holds raw observations: their mean is the statistics' mean, not ~0
    with open(result.checkpoint / "replay_buffer.pkl", "rb") as f:
        buf = pickle.load(f)["arrays"]["observations"]["observation"][:, 0, :]
    std = np.sqrt(rms.var)
    far = np.abs(rms.mean) > 2 * std
    assert far.any()  # some entries sit far from 0 in raw units (the end-effector position)
    assert np.all(np.abs(buf.mean(0) - rms.mean) <= 0.25 * std + 1e-6)

    # the periodic evaluation at step 100 saw observations normalised with exactly the step-100 statistics
    assert [s for s, _ in eval_steps] == [100, 200]
    _assert_normalised_with(pairs[eval_steps[0][1] : eval_steps[1][1]], s100)

    # resume: the statistics go on from the checkpoint's, not from zero
    assert recipes.train(_cfg(run, total_steps=300, **over), resume=True).steps == 300
    s300 = load_obs_stats(ckpts / "step_000000300")
    assert s300.obs_rms["observation"].count > c200 + 99.5

    # `uniros eval`: the policy sees the observations normalised with the checkpoint's statistics
    make_eval_env = evaluate_mod.make_eval_env
    monkeypatch.setattr(evaluate_mod, "make_eval_env", lambda *a, **k: _LastObs(make_eval_env(*a, **k)))
    del pairs[:]
    r = evaluate_checkpoint(run, RX_GOAL["id"], {"clock": "sim", "reward_type": "sparse"}, episodes=1)
    assert r.episodes == 1 and r.normalized_obs and r.to_dict()["normalized_obs"] is True
    _assert_normalised_with(pairs, s300)
    model, _, _ = load_policy(run)
    assert model.get_vec_normalize_env().obs_rms["observation"].count == s300.obs_rms["observation"].count

    # a checkpoint with statistics is never evaluated without them, nor resumed under another setting
    bare = tmp_path / "bare"
    shutil.copytree(ckpts / "step_000000300", bare)
    (bare / "vec_normalize.pkl").unlink()
    with pytest.raises(CheckpointError, match=r"normalize_obs.*vec_normalize.pkl is missing"):
        evaluate_checkpoint(bare, RX_GOAL["id"], {"clock": "sim", "reward_type": "sparse"}, episodes=1)
    with pytest.raises(CheckpointError, match="trained with normalize_obs: true; the config says normalize_obs: false"):
        recipes.train(_cfg(run, total_steps=400, normalize_obs=False, **over), resume=True)


@pytest.mark.slow
def test_async_multitask_dense_run_stores_raw_and_checkpoints_the_statistics(tmp_path: Path) -> None:
    run = tmp_path / "mt_async_norm"
    envs = [{"id": RX, "name": "rx"}, {"id": NED, "name": "ned"}]
    result = recipes.train(_cfg(run, envs=envs, total_steps=150, learner="async"))
    meta = read_meta(result.checkpoint)
    assert meta.algo == "AsyncTD3" and meta.normalize_obs and meta.pad_to == (28, 6)
    stats = load_obs_stats(result.checkpoint)
    rms = stats.obs_rms
    assert rms.mean.shape == (28,) and 150 <= rms.count < 160
    assert np.any(np.abs(rms.mean) > 2 * np.sqrt(rms.var))  # entries far from 0 in raw units
    # AsyncTD3's actor loop stores raw observations (SB3's _store_transition with VecNormalize)
    with open(result.checkpoint / "replay_buffer.pkl", "rb") as f:
        buf = pickle.load(f)["arrays"]["observations"][:, 0, :]
    assert buf.shape[0] == 150
    assert np.all(np.abs(buf.mean(0) - rms.mean) <= 0.25 * np.sqrt(rms.var) + 1e-6)
    assert np.abs(stats.normalize_obs(buf).mean(0)).max() < 0.5  # and normalising them centres them
    r = evaluate_checkpoint(run, NED, {"clock": "sim"}, episodes=1)  # padded, normalised as in training
    assert r.episodes == 1
