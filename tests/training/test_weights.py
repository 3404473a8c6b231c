"""Policy weights (training/weights.py): an exported actor acts as SB3's model does, and bad weights say what is wrong.

Real SB3 TD3 models (untrained: their random actors are as good a check of the arithmetic as trained ones) on a
Box env with bounds other than [-1, 1] and on a Dict env behind VecNormalize, saved by ``save_checkpoint``,
exported, loaded back and compared with ``model.predict`` on the same observations.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from uniros_async.training.checkpoint import CheckpointError, CheckpointMeta, save_checkpoint
from uniros_async.training.weights import OBS_STATS_FILE, WEIGHTS_FILE, export_weights, load_policy

pytestmark = pytest.mark.slow  # SB3 and torch: the first import in a process takes seconds


class _DictEnv(gym.Env[dict[str, np.ndarray], np.ndarray]):
    """A goal-env-shaped observation (three keys, not in sorted order) and an action box of [-0.5, 2]."""

    observation_space = gym.spaces.Dict(
        {
            "observation": gym.spaces.Box(-5.0, 5.0, (4,), np.float32),
            "desired_goal": gym.spaces.Box(-1.0, 1.0, (2,), np.float32),
            "achieved_goal": gym.spaces.Box(-1.0, 1.0, (2,), np.float32),
        }
    )
    action_space = gym.spaces.Box(-0.5, 2.0, (3,), np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action: np.ndarray) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        return self.observation_space.sample(), 0.0, False, False, {}


def _export(model: Any, tmp_path: Path, *, goal_env: bool) -> Path:
    meta = CheckpointMeta(step=1, obs_size=8 if goal_env else 3, action_size=3 if goal_env else 1, goal_env=goal_env,
                          pad_to=None)  # fmt: skip
    ckpt = save_checkpoint(model, tmp_path / "run", meta, replay_buffer=False)
    return export_weights(ckpt, tmp_path / "weights")


def test_box_policy_acts_as_sb3_predicts(tmp_path: Path) -> None:
    from stable_baselines3 import TD3

    env = gym.make("Pendulum-v1")  # action box [-2, 2]: the tanh output is scaled to it
    model = TD3("MlpPolicy", env, policy_kwargs={"net_arch": [16, 8]}, buffer_size=10, seed=3, device="cpu")
    out = _export(model, tmp_path, goal_env=False)
    assert sorted(p.name for p in out.iterdir()) == ["meta.json", WEIGHTS_FILE]
    policy = load_policy(out)
    obs = np.stack([env.observation_space.sample() for _ in range(64)])
    expected = np.stack([model.predict(o, deterministic=True)[0] for o in obs])
    np.testing.assert_allclose(policy(obs), expected, atol=1e-5)
    np.testing.assert_allclose(policy(obs[0]), expected[0], atol=1e-5)
    assert policy(obs[0]).shape == (1,)
    assert np.abs(expected).max() > 0.05  # the actor's actions are not all zero: the comparison could fail
    with pytest.raises(CheckpointError, match="takes 3 observation entries, got 5"):
        policy(np.zeros(5))
    env.close()


def test_dict_policy_with_obs_statistics_acts_as_sb3_predicts(tmp_path: Path) -> None:
    from stable_baselines3 import TD3
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    venv = VecNormalize(DummyVecEnv([_DictEnv]), norm_obs=True, norm_reward=False, clip_obs=2.0)
    venv.seed(0)
    venv.reset()
    for _ in range(50):  # statistics away from mean 0, var 1
        venv.step(np.array([venv.action_space.sample()]))
    model = TD3("MultiInputPolicy", venv, policy_kwargs={"net_arch": [16, 8]}, buffer_size=10, seed=4, device="cpu")
    out = _export(model, tmp_path, goal_env=True)
    assert (out / OBS_STATS_FILE).is_file()
    policy = load_policy(out)
    assert policy.get_vec_normalize_env() is None
    stats = model.get_vec_normalize_env()
    assert stats is not None
    raw = [_DictEnv.observation_space.sample() for _ in range(32)]
    for o in raw:
        o["observation"] = o["observation"] * 3.0  # some entries beyond clip_obs once normalised
        expected, _ = model.predict(stats.normalize_obs(o), deterministic=True)
        np.testing.assert_allclose(policy(o), expected, atol=1e-5)
        assert ((expected >= -0.5) & (expected <= 2.0)).all()
    batch = {k: np.stack([o[k] for o in raw]) for k in raw[0]}
    assert policy(batch).shape == (32, 3)
    with pytest.raises(CheckpointError, match="dict observation with keys"):
        policy(np.zeros(8))
    (out / OBS_STATS_FILE).unlink()
    with pytest.raises(CheckpointError, match=f"{OBS_STATS_FILE} is missing"):
        load_policy(out)
    venv.close()


def test_a_directory_without_weights_is_named(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match=f"no {WEIGHTS_FILE} in"):
        load_policy(tmp_path)
    np.savez(tmp_path / WEIGHTS_FILE, something=np.zeros(2))
    with pytest.raises(CheckpointError, match="lacks 'action_low'"):
        load_policy(tmp_path)
