"""The training pipeline end to end, a few hundred steps each (asserting the pipeline, not the success rate):
train, periodic evaluation, CSV curves, checkpoints, resume, evaluation of a checkpoint, multi-task padding,
HER, the asynchronous learner, and the clear errors for mismatched checkpoints."""

from __future__ import annotations

import csv
import dataclasses
import importlib.util
import json
import math
from pathlib import Path
from typing import Any

import gymnasium as gym
import pytest

from uniros_async.errors import ConfigError
from uniros_async.training.checkpoint import (
    CheckpointError,
    latest_checkpoint,
    load_replay_buffer,
    read_meta,
    save_checkpoint,
)
from uniros_async.training.config import train_config_from_dict
from uniros_async.training.evaluate import evaluate_checkpoint, load_policy
from uniros_async.training.recipes import TrainResult, train

pytestmark = pytest.mark.slow

RX = "uniros/Rx200Reach-v0"
NED = "uniros/Ned2Reach-v0"
RX_GOAL = {"id": "uniros/Rx200ReachGoal-v0", "kwargs": {"reward_type": "sparse"}}


def _cfg(run_dir: Path, **over: Any) -> Any:
    base: dict[str, Any] = {
        "name": run_dir.name,
        "run_dir": str(run_dir),
        "total_steps": 200,
        "envs": [RX],
        "td3": {"learning_starts": 50, "buffer_size": 5000, "batch_size": 32, "net_arch": [32, 32]},
        "eval": {"every_steps": 100, "episodes": 1},
        "checkpoint": {"every_steps": 100, "keep": 2},
        "progress_bar": False,
    }
    for key, value in over.items():
        base[key] = {**base[key], **value} if isinstance(value, dict) and isinstance(base.get(key), dict) else value
    return train_config_from_dict(base)


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def dense_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, TrainResult]:
    run = tmp_path_factory.mktemp("runs") / "dense"
    return run, train(_cfg(run))


def test_a_run_writes_curves_tensorboard_and_checkpoints(dense_run: tuple[Path, TrainResult]) -> None:
    run, result = dense_run
    assert result.steps == 200 and result.checkpoint.name == "step_000000200"
    assert {p.name for p in (run / "checkpoints").iterdir()} == {"latest", "step_000000100", "step_000000200"}
    meta = read_meta(result.checkpoint)
    assert (meta.step, meta.obs_size, meta.action_size, meta.goal_env, meta.pad_to) == (200, 28, 5, False, None)
    assert [(r["step"], r["task"]) for r in _rows(run / "eval.csv")] == [("100", "Rx200Reach"), ("200", "Rx200Reach")]
    episodes = _rows(run / "episodes.csv")
    assert len(episodes) == 2 and all(r["length"] == "100" for r in episodes)  # 100-step limit, no success yet
    assert json.loads((run / "final_eval.json").read_text())["step"] == 200
    assert any((run / "tb").rglob("events.out.tfevents.*"))
    # zero-shot on the emulated real arm (accelerated), the entry point of `uniros eval`
    r = evaluate_checkpoint(run, RX, {"clock": "sim", "robot": "emulated-real"}, episodes=1, seed=3)
    assert r.episodes == 1 and 1 <= r.mean_length <= 100 and math.isfinite(r.mean_return)
    # the episode either reached the goal, which ends it before the 100-step limit, or ran into that limit
    assert (r.successes == 1) == (r.mean_length < 100), r.summary()


def test_the_replay_buffer_comes_back_compact(dense_run: tuple[Path, TrainResult]) -> None:
    from stable_baselines3 import TD3

    run, result = dense_run
    assert (result.checkpoint / "replay_buffer.pkl").stat().st_size < 200_000  # 200 rows, not 5000
    env = gym.make(RX, clock="sim")
    try:
        model = TD3.load(result.checkpoint / "model.zip", env=env, device="cpu")
        assert model.replay_buffer.pos == 0
        assert load_replay_buffer(model, result.checkpoint) == 200
        assert model.replay_buffer.pos == 200 and not model.replay_buffer.full
        assert abs(model.replay_buffer.observations[:200]).sum() > 0
    finally:
        env.close()


def test_a_checkpoint_of_another_size_is_a_clear_error(dense_run: tuple[Path, TrainResult]) -> None:
    run, _ = dense_run
    with pytest.raises(
        CheckpointError,
        match=r"observation size 25 and action size 6, but the checkpoint's policy "
        r"takes observation size 28 and action size 5",
    ):
        evaluate_checkpoint(run, NED, {"clock": "sim"}, episodes=1)
    with pytest.raises(CheckpointError, match="is a goal env"):
        evaluate_checkpoint(run, "uniros/Rx200ReachGoal-v0", {"clock": "sim"}, episodes=1)
    with pytest.raises(CheckpointError, match="observation size 25 and action size 6"):
        train(_cfg(run, total_steps=300, envs=[NED]), resume=True)
    with pytest.raises(CheckpointError, match="no checkpoint at"):
        evaluate_checkpoint(run / "nothing", RX, {"clock": "sim"}, episodes=1)
    with pytest.raises(ConfigError, match="already holds checkpoints"):
        train(_cfg(run, total_steps=300))


def test_an_interrupted_checkpoint_write_leaves_the_last_one(dense_run: tuple[Path, TrainResult]) -> None:
    run, _ = dense_run
    before = latest_checkpoint(run)
    assert before is not None
    model, meta, _ = load_policy(run)

    class Boom(Exception):
        pass

    def broken_save(path: Any, *a: Any, **k: Any) -> None:
        Path(path).write_bytes(b"partial")
        raise Boom

    model.save = broken_save
    names = sorted(p.name for p in (run / "checkpoints").iterdir())
    with pytest.raises(Boom):
        save_checkpoint(model, run, dataclasses.replace(meta, step=999))
    assert latest_checkpoint(run) == before
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == names


def test_multitask_pads_samples_and_reports_per_env(tmp_path: Path) -> None:
    run = tmp_path / "mt"
    envs = [{"id": RX, "name": "rx_sim"}, {"id": NED, "name": "ned_real", "kwargs": {"robot": "emulated-real"}}]
    result = train(_cfg(run, envs=envs, total_steps=200, eval={"every_steps": 0}, checkpoint={"every_steps": 0}))
    meta = read_meta(result.checkpoint)
    assert meta.pad_to == (28, 6) and (meta.obs_size, meta.action_size) == (28, 6)
    assert {r.label for r in result.final_eval} == {"rx_sim", "ned_real"}
    assert {r["task"] for r in _rows(run / "episodes.csv")} <= {"rx_sim", "ned_real"}
    r = evaluate_checkpoint(run, NED, {"clock": "sim"}, episodes=1)  # padded as in training
    assert r.episodes == 1


def test_her_on_the_goal_env_and_its_resume(tmp_path: Path) -> None:
    run = tmp_path / "her"
    over = {
        "envs": [RX_GOAL],
        "td3": {"learning_starts": 100},
        "eval": {"every_steps": 0},
        "drop_observation": [13, 14, 15],
    }
    result = train(_cfg(run, total_steps=150, **over))
    meta = read_meta(result.checkpoint)
    assert meta.goal_env and meta.config["replay_buffer"] == "auto"  # auto: HER on goal envs
    assert meta.drop_observation == (13, 14, 15) and meta.obs_size == 21  # 24 goal-free entries, 3 dropped
    r = evaluate_checkpoint(run, RX_GOAL["id"], {"clock": "sim", "reward_type": "sparse"}, episodes=1)
    assert r.episodes == 1
    assert train(_cfg(run, total_steps=250, **over), resume=True).steps == 250  # an unfinished episode is closed
    with pytest.raises(ConfigError, match="replay_buffer: her needs goal envs"):
        train(_cfg(tmp_path / "her_bad", replay_buffer="her"))


@pytest.mark.skipif(importlib.util.find_spec("uniros_async.training.async_td3") is None, reason="no AsyncTD3 yet")
def test_the_async_learner_trains_checkpoints_and_resumes(tmp_path: Path) -> None:
    run = tmp_path / "async"
    over = {"learner": "async", "eval": {"every_steps": 0}, "checkpoint": {"every_steps": 0}}
    result = train(_cfg(run, total_steps=150, **over))
    assert read_meta(result.checkpoint).algo == "AsyncTD3"
    assert train(_cfg(run, total_steps=200, **over), resume=True).steps == 200
    model, meta, _ = load_policy(run)
    assert type(model).__name__ == "AsyncTD3" and meta.step == 200


def test_training_stops_once_every_env_reaches_eval_stop_success(tmp_path: Path) -> None:
    """With a reach tolerance of a metre every episode succeeds at its first step: the first evaluation (at 100)
    finds both envs at 100 %, training stops there, and the run still ends with its final evaluation and
    checkpoint. Without ``stop_success`` the same run goes on to ``total_steps``."""
    easy = {"reach_tolerance": 1.0}
    envs = [{"id": RX, "name": "rx200", "kwargs": easy}, {"id": NED, "name": "ned2", "kwargs": easy}]
    run = tmp_path / "stops"
    result = train(_cfg(run, envs=envs, total_steps=2000, eval={"stop_success": 0.9}))
    assert 100 <= result.steps < 200, f"training went on to step {result.steps}"
    assert {r.label: r.success_rate for r in result.final_eval} == {"rx200": 1.0, "ned2": 1.0}
    assert read_meta(latest_checkpoint(run)).step == result.steps  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"eval.stop_success"):
        _cfg(tmp_path / "bad", eval={"stop_success": 1.5})


def test_training_runs_with_the_set_up_heap_frozen(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Once set up, ``train`` freezes the agent process's heap (``priority.freeze_heap``, as the workers do after
    theirs): while it learns, the set-up's objects (modules, envs, model) are out of the collector's reach. After the
    run the heap is unfrozen again."""
    import gc

    from stable_baselines3 import TD3

    frozen_at_learn: list[int] = []
    real_learn = TD3.learn

    def spy(self: Any, *a: Any, **k: Any) -> Any:
        frozen_at_learn.append(gc.get_freeze_count())
        return real_learn(self, *a, **k)

    monkeypatch.setattr(TD3, "learn", spy)
    gc.unfreeze()  # whatever an earlier test in this process froze: train unfreezes only what it froze itself
    result = train(_cfg(tmp_path / "frozen", total_steps=60, eval={"every_steps": 0}, checkpoint={"every_steps": 0}))
    assert result.steps == 60
    assert len(frozen_at_learn) == 1 and frozen_at_learn[0] > 1000, frozen_at_learn  # the set-up's objects
    assert gc.get_freeze_count() == 0
