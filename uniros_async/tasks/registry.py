"""Tasks and their gymnasium ids: a registry open to user code, registered on ``import uniros_async``.

A task is an env class (a ``TaskEnv``, by ``"module:Class"`` entry point) with its default keyword arguments; an
env id is a task on a robot, registered with gymnasium. The ids that ship are the reach tasks on both arms::

    uniros/Rx200Reach-v0  uniros/Rx200ReachGoal-v0  uniros/Ned2Reach-v0  uniros/Ned2ReachGoal-v0
    uniros/Rx200ReachPixels-v0 (the goal seen by the camera only)

A package of your own registers its tasks and ids at import, without touching this module::

    from uniros_async.tasks.registry import register_env_id, register_task

    register_task("Push", "my_pkg.push:PushEnv", kwargs={"push_distance": 0.1})
    register_env_id("rx200", "Push")                           # "uniros/Rx200Push-v0"
    register_env_id("myarm", "Reach", env_id="my_pkg/MyarmReach-v0", kwargs={"goal_min": (0.1, -0.1, 0.05)})

Entry points are strings, so registering costs one gymnasium import (done when an id is registered, not when this
module is imported: ``import uniros_async`` registers the ids that ship right after gymnasium is first imported,
and that hook must find this module whole); MuJoCo, pinocchio and the env code load only when an env is made (a
transport-only process or a spawned worker does not pay for them). A worker process finds a user's id when the id
is given as ``"my_pkg:my_pkg/MyarmReach-v0"`` (gymnasium imports ``my_pkg`` first).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterator, Mapping
from types import MappingProxyType
from typing import Any

from uniros_async.errors import ConfigError
from uniros_async.registry import Registry, split_entry_point
from uniros_async.robots import get_robot_spec, robot_names

__all__ = [
    "ENV_IDS",
    "TaskSpec",
    "env_id_of",
    "register_env_id",
    "register_envs",
    "register_task",
    "task_names",
    "task_spec",
]

MAX_EPISODE_STEPS = 100
"""The episode length of the ids that ship (gymnasium's TimeLimit)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class TaskSpec:
    """One registered task.

    Attributes:
        name: the task's name, CamelCase (``"Reach"``); an id's default name is ``<Robot><name>-v0``.
        entry_point: the env class as ``"module:Class"``; it takes ``arm`` and keyword arguments.
        kwargs: the task's default keyword arguments (an id's own and then the caller's override them).
        max_episode_steps: the episode length of its ids (None: no TimeLimit).
    """

    name: str
    entry_point: str
    kwargs: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    max_episode_steps: int | None = MAX_EPISODE_STEPS


@dataclasses.dataclass(frozen=True)
class _EnvId:
    robot: str
    task: str
    kwargs: Mapping[str, Any]


class _EnvIds(Mapping[str, tuple[str, str]]):
    """The env id registry read as ``id -> (robot, task)``."""

    def __getitem__(self, env_id: str) -> tuple[str, str]:
        entry = _ENV_IDS.entries[env_id]
        assert isinstance(entry, _EnvId)  # the registry takes no entry points
        return entry.robot, entry.task

    def __iter__(self) -> Iterator[str]:
        return iter(_ENV_IDS.entries)

    def __len__(self) -> int:
        return len(_ENV_IDS)


_TASKS = Registry[TaskSpec]("task", note="register_task adds one")


def _describe_id(entry: _EnvId | str) -> str:
    return f"for {(entry.robot, entry.task)}" if isinstance(entry, _EnvId) else entry


_ENV_IDS = Registry[_EnvId]("env id", describe=_describe_id, overridable=False)

ENV_IDS: Mapping[str, tuple[str, str]] = _EnvIds()
"""Every id registered through this module (built-in and user-registered), as ``id -> (robot, task)``."""

_NAME = re.compile(r"[A-Z][A-Za-z0-9]*")


def register_task(
    name: str,
    entry_point: str,
    *,
    kwargs: Mapping[str, Any] | None = None,
    max_episode_steps: int | None = MAX_EPISODE_STEPS,
    override: bool = False,
) -> TaskSpec:
    """Register a task; ``register_env_id`` then puts it on a robot as a gymnasium id.

    Registering the same task again is a no-op, so a module may register at import however often it is imported.

    Args:
        name: CamelCase name, e.g. ``"Push"``.
        entry_point: ``"module:Class"`` of the env class (a ``TaskEnv`` taking ``arm`` and keyword arguments).
        kwargs: default keyword arguments of its envs.
        max_episode_steps: episode length of its ids (None: no time limit).
        override: replace another task already registered under ``name``.

    Returns:
        The registered TaskSpec.

    Raises:
        ConfigError: a malformed name or entry point, or the name is taken and ``override`` is False.
    """
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise ConfigError(f"register_task: the name must be CamelCase like 'Push', got {name!r}")
    try:
        split_entry_point(entry_point, "")
    except ConfigError:
        raise ConfigError(
            f"register_task({name!r}): expected an entry point 'module:Class', got {entry_point!r}"
        ) from None
    if max_episode_steps is not None and not (isinstance(max_episode_steps, int) and max_episode_steps > 0):
        raise ConfigError(f"register_task({name!r}): max_episode_steps must be a positive int or None")
    spec = TaskSpec(
        name=name,
        entry_point=entry_point,
        kwargs=MappingProxyType(dict(kwargs or {})),
        max_episode_steps=max_episode_steps,
    )
    return _TASKS.register(name, spec, override=override)  # type: ignore[return-value]  # no entry points


def task_names() -> tuple[str, ...]:
    """The registered tasks' names, sorted."""
    return _TASKS.names()


def task_spec(name: str) -> TaskSpec:
    """The task registered as ``name``.

    Raises:
        ConfigError: none is; the message lists the registered tasks and the closest one.
    """
    return _TASKS.get(name)


def env_id_of(robot: str, task: str, namespace: str = "uniros") -> str:
    """The default id of ``task`` on ``robot``: ``"uniros/Rx200Reach-v0"`` for ``("rx200", "Reach")``.

    The robot's name in CamelCase (``"my_arm"`` -> ``"MyArm"``) followed by the task's name, version 0.
    """
    camel = "".join(part[:1].upper() + part[1:] for part in re.split(r"[_\-\s]+", robot) if part)
    return f"{namespace}/{camel}{task}-v0"


def register_env_id(
    robot: str,
    task: str,
    *,
    env_id: str | None = None,
    kwargs: Mapping[str, Any] | None = None,
    max_episode_steps: int | None = None,
) -> str:
    """Register a gymnasium id for ``task`` on ``robot``: ``gymnasium.make(id)`` then makes that env.

    The env gets ``arm=robot``, the task's default kwargs, then ``kwargs`` (a caller's kwargs at ``make`` override
    all of them). Registering the same id with the same arguments again is a no-op.

    Args:
        robot: a registered robot's name (``uniros_async.robots.register_robot``).
        task: a registered task's name (``register_task``).
        env_id: the id; None: ``env_id_of(robot, task)``, e.g. ``"uniros/MyarmReach-v0"``.
        kwargs: this id's own default keyword arguments (e.g. a goal box that suits the robot).
        max_episode_steps: None: the task's.

    Returns:
        The registered id.

    Raises:
        ConfigError: an unknown robot or task (with the closest registered name), or the id is taken by another
            registration (of this module or of gymnasium).
    """
    spec = task_spec(task)
    if robot not in robot_names():
        get_robot_spec(robot)  # ConfigError naming the registered robots and the closest one
    env_id = env_id or env_id_of(robot, task)
    own = {"arm": robot, **spec.kwargs, **(kwargs or {})}
    steps = spec.max_episode_steps if max_episode_steps is None else max_episode_steps
    entry = _EnvId(robot, task, own)
    if env_id in _ENV_IDS:
        _ENV_IDS.register(env_id, entry)  # a no-op for the same id, else ConfigError naming the one registered
        return env_id
    from gymnasium.envs.registration import register, registry

    if env_id in _ENV_IDS:  # registered meanwhile: importing gymnasium just now registered the ids that ship
        return register_env_id(robot, task, env_id=env_id, kwargs=kwargs, max_episode_steps=max_episode_steps)
    if env_id in registry:
        raise ConfigError(f"env id {env_id!r} is already a gymnasium id ({registry[env_id].entry_point})")
    register(
        id=env_id,
        entry_point=spec.entry_point,
        max_episode_steps=steps,
        kwargs=own,
        disable_env_checker=True,  # step() validates actions itself; the tests run the full checkers
    )
    _ENV_IDS.register(env_id, entry)
    return env_id


def _register_tasks() -> None:
    """The tasks that ship (no gymnasium import: a task is a name, an entry point and defaults)."""
    register_task("Reach", "uniros_async.tasks.reach:ReachEnv")
    register_task("ReachGoal", "uniros_async.tasks.reach:ReachGoalEnv")
    register_task("ReachPixels", "uniros_async.tasks.reach_pixels:ReachPixelsEnv")


def register_envs() -> None:
    """Register the ids that ship (idempotent): the reach tasks on rx200 and ned2."""
    _register_tasks()
    for robot in ("rx200", "ned2"):
        for task in ("Reach", "ReachGoal"):
            register_env_id(robot, task)
    register_env_id("rx200", "ReachPixels")  # the target seen by the scene camera only (tasks/reach_pixels.py)


_register_tasks()
