"""Training: SB3 TD3 / TD3+HER recipes, the multi-task trainer (the paper's Algorithm 1), checkpoints,
evaluation and learning-curve plots; ``uniros train|eval|plot`` on the command line.

Exports load lazily: importing this package imports neither torch nor SB3, and never the asynchronous learner
(``uniros_async.training.async_td3``) unless ``AsyncTD3`` is asked for.
"""

from __future__ import annotations

from uniros_async._lazy import lazy_exports

__all__ = [
    "AsyncTD3",
    "CheckpointError",
    "EvalResult",
    "TaskSamplerEnv",
    "TrainConfig",
    "TrainResult",
    "TrainingInterrupted",
    "evaluate_checkpoint",
    "evaluate_policy",
    "load_policy",
    "load_train_config",
    "plot_runs",
    "train",
    "train_config_from_dict",
]

_WHERE = {
    "AsyncTD3": "async_td3",
    "CheckpointError": "checkpoint",
    "EvalResult": "evaluate",
    "TaskSamplerEnv": "multitask",
    "TrainConfig": "config",
    "TrainResult": "recipes",
    "TrainingInterrupted": "recipes",
    "evaluate_checkpoint": "evaluate",
    "evaluate_policy": "evaluate",
    "load_policy": "evaluate",
    "load_train_config": "config",
    "plot_runs": "plot",
    "train": "recipes",
    "train_config_from_dict": "config",
}


__getattr__, __dir__ = lazy_exports(__name__, _WHERE)
