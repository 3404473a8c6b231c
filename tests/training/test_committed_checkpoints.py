"""The policies committed under docs/results/checkpoints still do what docs/results.md says they do.

A change to the envs (observation, reward, action scaling, safety, timing) that breaks a published result shows
up here: each checkpoint is evaluated with `evaluate_checkpoint` (what `uniros eval` runs) on the first episodes of
the 200-episode transfer runs of docs/results.md section 3 (seed 0, accelerated sim, in-process), where it
succeeded in every one of them.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from uniros_async.training.evaluate import evaluate_checkpoint

pytestmark = pytest.mark.slow

CHECKPOINTS = Path(__file__).resolve().parents[2] / "docs" / "results" / "checkpoints"
EPISODES = 10

CASES = [
    pytest.param(
        "rx200_reach_dense_td3_uniros",
        "uniros/Rx200Reach-v0",
        {"reward_type": "dense", "action_mode": "delta"},
        id="dense-td3",
    ),
    pytest.param(
        "rx200_reach_goal_her_norm",
        "uniros/Rx200ReachGoal-v0",
        {"reward_type": "sparse", "action_mode": "delta", "unsafe_action": "project"},
        id="her-normalised",
    ),
]


@pytest.mark.parametrize("name,env_id,kwargs", CASES)
@pytest.mark.parametrize("robot", ["sim", "emulated-real"])
def test_a_committed_policy_still_reaches_its_goals(name: str, env_id: str, kwargs: dict[str, str], robot: str) -> None:
    ckpt = CHECKPOINTS / name
    if not ckpt.is_dir():
        pytest.fail(f"{ckpt} is missing: docs/results.md reproduces its figures from it")
    result = evaluate_checkpoint(ckpt, env_id, {**kwargs, "clock": "sim", "robot": robot}, episodes=EPISODES, seed=0)
    assert result.successes >= EPISODES - 1, result.summary()


@pytest.mark.parametrize("name,env_id,kwargs", CASES)
def test_eval_defaults_to_the_kwargs_the_policy_was_trained_with(
    name: str, env_id: str, kwargs: dict[str, str]
) -> None:
    """``uniros eval`` without ``--env-kwargs`` evaluates on the env as trained (action mode, reward, ...): the
    kwargs come from the checkpoint's config, the clock left to the evaluation; another env id gets none."""
    from uniros_async.training.checkpoint import find_checkpoint, read_meta
    from uniros_async.training.evaluate import training_kwargs

    meta = read_meta(find_checkpoint(CHECKPOINTS / name))
    assert training_kwargs(meta, env_id) == kwargs
    assert training_kwargs(meta, env_id, label="not-a-label") is None
    assert training_kwargs(meta, "uniros/Ned2Reach-v0") is None
