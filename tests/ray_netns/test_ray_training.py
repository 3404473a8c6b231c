"""Training on workers placed by Ray: SB3's TD3, the asynchronous learner and ``uniros train`` (``placement: ray``)
on the head node (the agent's), the envs on the arm node, on a real two-node Ray cluster."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import torch
from stable_baselines3 import TD3

from uniros_async.runtime import make_vec
from uniros_async.training.async_td3 import AsyncTD3

RX, NED = "uniros/Rx200Reach-v0", "uniros/Ned2Reach-v0"
ARM = {"worker": {"ray": {"resources": {"rx200_arm": 1}}}}
SMALL: dict[str, Any] = dict(
    learning_starts=50, batch_size=32, buffer_size=5_000, policy_kwargs={"net_arch": [32, 32]}, seed=0, device="cpu"
)

pytestmark = pytest.mark.usefixtures("nothing_left")


def test_sb3_td3_learns_a_few_hundred_steps_on_ray_placed_workers(cluster: dict[str, Any]) -> None:
    torch.set_num_threads(1)
    venv = make_vec([(RX, ARM), NED], backend="ray", clock="sim")
    try:
        assert venv._sup.workers[0].process.node_id == cluster["arm_id"]
        model = TD3("MlpPolicy", venv.as_sb3(), train_freq=(4, "step"), gradient_steps=1, verbose=0, **SMALL)
        model.learn(total_timesteps=300)
        assert model.num_timesteps >= 300
        assert model.replay_buffer is not None and model.replay_buffer.size() >= 150  # 2 envs: 150 steps each
    finally:
        venv.close()


def test_the_async_learner_on_the_head_with_every_env_on_the_arm_node(cluster: dict[str, Any]) -> None:
    torch.set_num_threads(1)
    on_arm = {"worker": {"ray": {"node_id": cluster["arm_id"]}}}
    venv = make_vec([(RX, ARM), (NED, on_arm)], backend="ray", clock="sim")
    try:
        nodes = {w.process.node_id for w in venv._sup.workers}
        assert nodes == {cluster["arm_id"]} and cluster["arm_id"] != cluster["head_id"]  # the learner: the head
        assert all(w.process.worker_uri.startswith("tcp://") for w in venv._sup.workers)
        model = AsyncTD3("MlpPolicy", venv.as_sb3(), **SMALL)
        model.learn(300)
        assert model.num_timesteps >= 300
        assert model.learner_stats["updates"] > 0  # the learner thread trained while the envs stepped on the arm node
    finally:
        venv.close()


def test_uniros_train_with_placement_ray_trains_on_the_arm_node(cluster: dict[str, Any], tmp_path: Path) -> None:
    # half of the arm node's rx200_arm each: the training env and the evaluation env both fit there, nowhere else
    config = tmp_path / "ray.yaml"
    config.write_text(
        "name: ray\n"
        "seed: 0\n"
        "total_steps: 200\n"
        "placement: ray\n"
        "learner: async\n"
        "envs:\n"
        "  - {id: uniros/Rx200Reach-v0, kwargs: {worker: {ray: {resources: {rx200_arm: 0.5}}}}}\n"
        "td3: {learning_starts: 50, buffer_size: 5000, net_arch: [32, 32], batch_size: 32}\n"
        "eval: {every_steps: 100, episodes: 1}\n"
        "checkpoint: {every_steps: 100}\n"
    )
    run = tmp_path / "run"
    env = dict(os.environ, RAY_ADDRESS=cluster["address"])
    proc = subprocess.run(
        [sys.executable, "-m", "uniros_async.cli", "train", str(config), "--run-dir", str(run), "--no-progress"],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
        check=False,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-6000:]
    assert (run / "checkpoints" / "latest").exists()
