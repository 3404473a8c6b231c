"""TaskEnv: a RobotEnv plus a task's spaces, observation, reward and termination.

A new task on an existing robot is one TaskEnv subclass and its settings: set ``action_space`` and
``observation_space``, implement the three hooks of RobotEnv (``_action_to_target``, ``_compute_returns``,
``_on_reset``), and call ``self._start()`` at the end of ``__init__``. The same class then runs on the sim arm,
a sim in another process, the emulated real arm and a real arm: only ``robot=`` changes
(docs/howto/add-a-task.md).
"""

from __future__ import annotations

from typing import Any, ClassVar

from uniros_async.config import ConfigModel, closest, problems_error
from uniros_async.envs.config import EnvConfig
from uniros_async.envs.robot import RobotEnv
from uniros_async.envs.safety import SafetyConfig
from uniros_async.errors import ConfigError

__all__ = ["TaskEnv", "parse_kwargs", "split_kwargs"]


def parse_kwargs(task_cls: type, kwargs: dict[str, Any]) -> tuple[EnvConfig, Any]:
    """Split and validate an env's keyword arguments: the EnvConfig keys, and the task's own settings.

    The task's settings are validated by its ``TASK_CONFIG`` (a ConfigModel) if it has one, and returned as that
    model; a task with only ``TASK_KEYS`` gets the dict of the keys given.

    Raises:
        ConfigError: one line per problem: an unknown keyword argument (with the closest valid one, or the list of
            all), or a bad value (the key, what was expected, what was given).
    """
    task_model: type[ConfigModel] | None = getattr(task_cls, "TASK_CONFIG", None)
    task_keys = task_model.field_names() if task_model is not None else tuple(getattr(task_cls, "TASK_KEYS", ()))
    env_keys = EnvConfig.field_names()
    problems: list[tuple[str, str]] = []
    for key in kwargs:
        if key not in env_keys and key not in task_keys:
            valid = sorted({*task_keys, *env_keys})
            near = closest(key, valid)
            hint = f"did you mean {near!r}?" if near else f"valid: {', '.join(valid)}"
            problems.append((str(key), f"unknown keyword argument; {hint}"))
    config: EnvConfig | None = None
    task: Any = {k: v for k, v in kwargs.items() if k in task_keys and k not in env_keys}
    try:
        config = EnvConfig(**{k: v for k, v in kwargs.items() if k in env_keys})
    except ConfigError as exc:
        problems += getattr(exc, "problems", None) or [("", str(exc))]
    if task_model is not None:
        try:
            task = task_model(**task)
        except ConfigError as exc:
            problems += getattr(exc, "problems", None) or [("", str(exc))]
    if problems or config is None:
        raise problems_error(problems, where=task_cls.__name__)
    return config, task


def split_kwargs(task_cls: type, kwargs: dict[str, Any]) -> tuple[EnvConfig, dict[str, Any]]:
    """``parse_kwargs`` with the task's settings as a dict of the keys given (validated values).

    Raises:
        ConfigError: as ``parse_kwargs``.
    """
    config, task = parse_kwargs(task_cls, kwargs)
    if isinstance(task, ConfigModel):
        return config, {k: getattr(task, k) for k in task.model_fields_set}
    return config, dict(task)


class TaskEnv(RobotEnv):
    """Base of every task (see the module docstring)."""

    TASK_KEYS: tuple[str, ...] = ()
    """The task's own keyword arguments (besides EnvConfig's); ``TASK_CONFIG``'s keys where it has one."""
    TASK_CONFIG: ClassVar[type[ConfigModel] | None] = None
    """The task's settings as a ConfigModel (types, defaults, checks); None: ``TASK_KEYS`` unchecked."""

    def __init__(self, arm: str, config: EnvConfig, safety: SafetyConfig | None = None) -> None:
        super().__init__(arm, config, safety)
