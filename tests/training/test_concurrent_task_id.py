"""``task_id_in_obs`` in a concurrent run: every observation the policy sees, the replay buffer stores and the
evaluations step carries its env's one-hot index, and a checkpoint of such a run evaluates one env by its label.

The envs are real worker processes on the sim clock (the index is the same on the wall clock; the real-time path is
test_realtime_training.py's)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from uniros_async.errors import CheckpointError
from uniros_async.training.concurrent import open_concurrent_env
from uniros_async.training.config import train_config_from_dict
from uniros_async.training.evaluate import evaluate_checkpoint
from uniros_async.training.recipes import train

pytestmark = pytest.mark.slow

EPISODE_STEPS = 3
KW = {"clock": "sim", "max_episode_steps": EPISODE_STEPS}
SPECS = [
    ("rx200_sim", "uniros/Rx200Reach-v0", dict(KW)),
    ("ned2_sim", "uniros/Ned2Reach-v0", dict(KW)),
]


def test_every_observation_ends_with_its_envs_one_hot_index() -> None:
    venv = open_concurrent_env(SPECS, task_id=True)
    try:
        # the rx200's 28 entries (the larger) and two for the index
        assert venv.observation_space.shape == (30,)
        ids = np.eye(2, dtype=np.float32)
        obs = venv.reset()
        assert obs.shape == (2, 30) and np.array_equal(obs[:, -2:], ids)
        assert np.all(venv.observation_space.contains(o) for o in obs)
        for step in range(1, EPISODE_STEPS + 1):
            obs, _, dones, infos = venv.step(np.zeros((2, 6), np.float32))
            assert np.array_equal(obs[:, -2:], ids)
            assert bool(np.all(dones)) is (step == EPISODE_STEPS)
        # the observation an episode ended on (the replay buffer's next observation) carries the index too, and
        # differs from the reset's that replaced it
        for i, info in enumerate(infos):
            final = info["terminal_observation"]
            assert final.shape == (30,) and np.array_equal(final[-2:], ids[i])
            assert not np.array_equal(final, obs[i])
    finally:
        venv.close()


def test_a_concurrent_run_with_task_ids_trains_evaluates_and_its_checkpoint_evaluates_by_label(tmp_path: Path) -> None:
    run = tmp_path / "ids"
    cfg: dict[str, Any] = {
        "name": run.name,
        "run_dir": str(run),
        "total_steps": 4 * EPISODE_STEPS,
        "envs": [{"id": env_id, "name": label} for label, env_id, _ in SPECS],
        "env_defaults": KW,
        "placement": "workers",
        "concurrent": True,
        "task_id_in_obs": True,
        "td3": {"learning_starts": 4, "buffer_size": 1000, "batch_size": 8, "net_arch": [16, 16]},
        "eval": {"every_steps": 0, "episodes": 1, "final_episodes": 2},
        "checkpoint": {"every_steps": 0},
        "progress_bar": False,
    }
    result = train(train_config_from_dict(cfg))
    final = json.loads((run / "final_eval.json").read_text())
    assert [(r["label"], r["episodes"]) for r in final["results"]] == [("rx200_sim", 2), ("ned2_sim", 2)]

    from uniros_async.training.checkpoint import read_meta

    meta = read_meta(result.checkpoint)
    assert (meta.obs_size, meta.task_id_size, meta.pad_to, meta.labels) == (30, 2, (28, 6), ("rx200_sim", "ned2_sim"))
    # one env alone, outside the vector env: padded, and given the index of the label it trained under
    res = evaluate_checkpoint(result.checkpoint, "uniros/Ned2Reach-v0", dict(KW), episodes=1, label="ned2_sim")
    assert res.episodes == 1
    with pytest.raises(CheckpointError, match=r"takes a task index; give the env one of its training labels"):
        evaluate_checkpoint(result.checkpoint, "uniros/Ned2Reach-v0", dict(KW), episodes=1)
