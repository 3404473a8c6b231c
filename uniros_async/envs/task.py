"""TaskEnv: a RobotEnv plus a task's spaces, observation, reward and termination.

A new task on an existing robot is one TaskEnv subclass and its settings: set ``action_space`` and
``observation_space``, implement the three hooks of RobotEnv (``_action_to_target``, ``_compute_returns``,
``_on_reset``), and call ``self._start()`` at the end of ``__init__``. The same class then runs on the sim arm,
a sim in another process, the emulated real arm and a real arm: only ``robot=`` changes
(docs/howto/add-a-task.md).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from uniros_async.envs.config import EnvConfig
from uniros_async.envs.robot import RobotEnv
from uniros_async.envs.safety import SafetyConfig
from uniros_async.errors import ConfigError

__all__ = ["TaskEnv", "split_kwargs"]


def split_kwargs(task_cls: type, kwargs: dict[str, Any]) -> tuple[EnvConfig, dict[str, Any]]:
    """EnvConfig fields out of ``kwargs``; anything that is neither an EnvConfig field nor in
    ``task_cls.TASK_KEYS`` is a ConfigError listing all valid keyword arguments."""
    cfg, rest = EnvConfig.split(kwargs)
    task_keys: tuple[str, ...] = getattr(task_cls, "TASK_KEYS", ())
    unknown = sorted(set(rest) - set(task_keys))
    if unknown:
        valid = sorted(set(task_keys) | {f.name for f in dataclasses.fields(EnvConfig)})
        raise ConfigError(f"{task_cls.__name__}: unknown keyword argument(s) {unknown}; valid: {valid}")
    return cfg, rest


class TaskEnv(RobotEnv):
    """Base of every task (see the module docstring)."""

    TASK_KEYS: tuple[str, ...] = ()

    def __init__(self, arm: str, config: EnvConfig, safety: SafetyConfig | None = None) -> None:
        super().__init__(arm, config, safety)
