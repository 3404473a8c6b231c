"""Multi-task training envs: the UniROS paper's Algorithm 1 as one gymnasium env that SB3 can train on.

``TaskSamplerEnv`` holds several envs (rx200 and ned2, sim and emulated real) padded to common observation and
action sizes (``envs.wrappers.PadSpaces``: zeros appended to observations, extra action entries ignored). Each
``reset`` samples one of them uniformly (the episode's task); ``step`` steps that env only. So SB3 TD3 over it is
Algorithm 1: sample an env per episode, collect its transitions into the one replay buffer, update the one
policy after every step. Every info carries ``info["task"]`` (the env's label) and ``info["task_index"]``, so
success can be reported per env.

``build_env`` makes one env for training or evaluation, in the agent's process (``gymnasium.make``) or in a
worker process (``uniros_async.make``, a proxy over shared memory), padded when asked.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from uniros_async.envs.wrappers import PadSpaces
from uniros_async.errors import ConfigError

__all__ = [
    "DropObservation",
    "TaskIdObservation",
    "TaskSamplerEnv",
    "build_env",
    "space_sizes",
    "task_id_box",
    "task_id_space",
    "with_task_id",
]


def _vector_box(space: gym.Space[Any]) -> gym.spaces.Box:
    if isinstance(space, gym.spaces.Dict):
        space = space.spaces["observation"]
    if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
        raise ConfigError(f"expected a 1-D Box observation (or a Dict with a 1-D 'observation'), got {space}")
    return space


def space_sizes(env: gym.Env[Any, Any]) -> tuple[int, int]:
    """(observation size, action size) of an env (the ``observation`` key's size for a goal env)."""
    act = env.action_space
    if not isinstance(act, gym.spaces.Box) or len(act.shape) != 1:
        raise ConfigError(f"expected a 1-D Box action space, got {act}")
    return int(_vector_box(env.observation_space).shape[0]), int(act.shape[0])


def build_env(
    env_id: str,
    kwargs: dict[str, Any],
    *,
    placement: str = "inprocess",
    pad_to: tuple[int, int] | None = None,
    drop_observation: tuple[int, ...] = (),
    delay_aware: tuple[int, bool] | None = None,
) -> gym.Env[Any, Any]:
    """Make one env (with its registered time limit), drop observation entries, add the delay-aware ones, and pad
    it to ``pad_to = (obs_size, action_size)``.

    Args:
        placement: ``inprocess`` (``gymnasium.make`` here), ``workers`` (``uniros_async.make``: its own process) or
            ``ray`` (``uniros_async.make(..., backend="ray")``: a process on the node Ray places it on).
        drop_observation: see ``DropObservation``.
        delay_aware: ``(action_history, observation_age)`` of ``envs.delay_aware.DelayAwareObservation``, or None.

    Raises:
        ConfigError: an unknown id or keyword argument, or an env larger than ``pad_to``.
        WorkerError: the worker failed to start (``workers``).
    """
    from uniros_async.runtime.envargs import check_env_args

    check_env_args(env_id, kwargs)
    if placement == "inprocess":
        env: gym.Env[Any, Any] = gym.make(env_id, **kwargs)
    elif placement in ("workers", "ray"):
        from uniros_async.runtime import make

        env = make(env_id, backend="local" if placement == "workers" else "ray", **kwargs)
    else:
        raise ConfigError(f"placement must be 'inprocess', 'workers' or 'ray', got {placement!r}")
    try:
        if drop_observation:
            env = DropObservation(env, tuple(drop_observation))
        if delay_aware is not None:
            from uniros_async.envs.delay_aware import DelayAwareObservation

            env = DelayAwareObservation(env, action_history=delay_aware[0], observation_age=delay_aware[1])
        if pad_to is not None and space_sizes(env) != tuple(pad_to):
            env = PadSpaces(env, *pad_to)
    except BaseException:
        env.close()
        raise
    return env


class _VectorObservationWrapper(gym.ObservationWrapper[Any, Any, Any]):
    """An observation wrapper that changes the vector observation (the ``observation`` key of a goal env) with
    ``_vector(vec)`` and leaves a goal env's goals alone; subclasses call ``_set_vector_space(box)``."""

    def _set_vector_space(self, new: gym.spaces.Box) -> None:
        self._goal = isinstance(self.env.observation_space, gym.spaces.Dict)
        if self._goal:
            self.observation_space = gym.spaces.Dict({**self.env.observation_space.spaces, "observation": new})  # type: ignore[attr-defined]
        else:
            self.observation_space = new

    def _vector(self, vec: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def observation(self, observation: Any) -> Any:
        if self._goal:
            return {**observation, "observation": self._vector(np.asarray(observation["observation"]))}
        return self._vector(np.asarray(observation))


class DropObservation(_VectorObservationWrapper):
    """Remove entries ``indices`` from the vector observation (the ``observation`` key of a goal env).

    For HER the policy's ``observation`` must not depend on the goal: relabelling replaces ``desired_goal`` only,
    so goal-dependent entries would contradict it (the reach goal envs leave them out themselves).

    Raises:
        ConfigError: an index outside the observation.
    """

    def __init__(self, env: gym.Env[Any, Any], indices: tuple[int, ...]) -> None:
        super().__init__(env)
        box = _vector_box(env.observation_space)
        n = box.shape[0]
        bad = [i for i in indices if not 0 <= i < n]
        if bad:
            raise ConfigError(f"drop_observation {bad} outside the observation of size {n}")
        self._keep = np.array([i for i in range(n) if i not in set(indices)], dtype=np.intp)
        self._set_vector_space(gym.spaces.Box(box.low[self._keep], box.high[self._keep], dtype=np.float32))

    def _vector(self, vec: np.ndarray) -> np.ndarray:
        return vec[self._keep]


class TaskIdObservation(_VectorObservationWrapper):
    """Append a one-hot task index (``index`` of ``n_tasks``) to the observation (the ``observation`` key)."""

    def __init__(self, env: gym.Env[Any, Any], index: int, n_tasks: int) -> None:
        super().__init__(env)
        self._onehot = np.zeros(n_tasks, np.float32)
        self._onehot[index] = 1.0
        self._set_vector_space(task_id_box(_vector_box(env.observation_space), n_tasks))

    def _vector(self, vec: np.ndarray) -> np.ndarray:
        out: np.ndarray = with_task_id(vec, self._onehot)
        return out


def task_id_box(box: gym.spaces.Box, n_tasks: int) -> gym.spaces.Box:
    """``box`` (1-D) with ``n_tasks`` one-hot entries in [0, 1] appended."""
    return gym.spaces.Box(
        np.concatenate([box.low, np.zeros(n_tasks, np.float32)]).astype(np.float32, copy=False),
        np.concatenate([box.high, np.ones(n_tasks, np.float32)]).astype(np.float32, copy=False),
        dtype=np.float32,
    )


def task_id_space(space: gym.Space[Any], n_tasks: int) -> gym.Space[Any]:
    """``space`` (a 1-D Box, or a goal env's Dict) with ``n_tasks`` one-hot entries appended to its vector.

    Raises:
        ConfigError: no 1-D Box to append to.
    """
    new = task_id_box(_vector_box(space), n_tasks)
    if isinstance(space, gym.spaces.Dict):
        return gym.spaces.Dict({**space.spaces, "observation": new})
    return new


def with_task_id(obs: Any, onehot: np.ndarray) -> Any:
    """``obs`` (a vector, a batch of vectors, or a goal env's dict of them) with ``onehot`` appended to its vector
    (``onehot`` one row per batch row, or one row for all)."""
    if isinstance(obs, dict):
        return {**obs, "observation": with_task_id(obs["observation"], onehot)}
    return np.concatenate([obs, onehot], axis=-1).astype(np.float32, copy=False)


def _union(spaces: list[gym.spaces.Box]) -> gym.spaces.Box:
    low = np.min(np.stack([s.low for s in spaces]), axis=0)
    high = np.max(np.stack([s.high for s in spaces]), axis=0)
    return gym.spaces.Box(low, high, dtype=np.float32)


class TaskSamplerEnv(gym.Env[Any, Any]):
    """One env per episode, sampled uniformly from ``envs`` (see the module docstring).

    The envs must already share observation and action sizes (``build_env(..., pad_to=...)``); the observation
    space is the union of their bounds and the action space their intersection ([-1, 1] for the reach envs).
    A goal env's ``compute_reward`` is the first env's: the reach reward is the same function for every arm.
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, envs: Sequence[gym.Env[Any, Any]], labels: Sequence[str], *, seed: int | None = None) -> None:
        if not envs or len(envs) != len(labels):
            raise ConfigError(f"TaskSamplerEnv needs one label per env, got {len(envs)} envs, {len(labels)} labels")
        self.envs = list(envs)
        self.labels = list(labels)
        sizes = {space_sizes(e) for e in self.envs}
        if len(sizes) != 1:
            raise ConfigError(
                "TaskSamplerEnv: envs differ in (observation, action) size: "
                + ", ".join(f"{lab}: {space_sizes(e)}" for lab, e in zip(self.labels, self.envs, strict=True))
                + " (pad them with build_env(..., pad_to=...))"
            )
        first = self.envs[0].observation_space
        self._goal = isinstance(first, gym.spaces.Dict)
        if any(isinstance(e.observation_space, gym.spaces.Dict) != self._goal for e in self.envs):
            raise ConfigError(f"TaskSamplerEnv: mixing goal and standard envs: {self.labels}")
        obs_box = _union([_vector_box(e.observation_space) for e in self.envs])
        if self._goal:
            self.observation_space = gym.spaces.Dict({**first.spaces, "observation": obs_box})  # type: ignore[attr-defined]
        else:
            self.observation_space = obs_box
        acts = [e.action_space for e in self.envs]
        self.action_space = gym.spaces.Box(
            np.max(np.stack([a.low for a in acts]), axis=0),  # type: ignore[attr-defined]
            np.min(np.stack([a.high for a in acts]), axis=0),  # type: ignore[attr-defined]
            dtype=np.float32,
        )
        self._task_rng = np.random.default_rng(seed)
        self.current = 0
        self.episodes = [0] * len(self.envs)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        """Sample the episode's env and reset it; a seed reseeds the sampler and every env."""
        super().reset(seed=seed)
        if seed is not None:
            self._task_rng = np.random.default_rng(seed)
            for i, env in enumerate(self.envs):
                env.reset(seed=seed + 1000 * (i + 1))
        self.current = int(self._task_rng.integers(len(self.envs)))
        self.episodes[self.current] += 1
        obs, info = self.envs[self.current].reset(options=options)
        return obs, self._tag(info)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """Step the current episode's env."""
        obs, reward, terminated, truncated, info = self.envs[self.current].step(action)
        return obs, float(reward), bool(terminated), bool(truncated), self._tag(info)

    def compute_reward(self, achieved_goal: Any, desired_goal: Any, info: Any) -> Any:
        """The goal envs' reward (HER relabelling)."""
        env = self.envs[0]
        fn = getattr(env.unwrapped, "compute_reward", None)
        if fn is not None:
            return fn(achieved_goal, desired_goal, info)
        return env.unwrapped.call("compute_reward", achieved_goal, desired_goal, info)  # type: ignore[attr-defined]

    def __getattr__(self, name: str) -> Any:
        # task settings (reward_type, reach_tolerance, ...) of the first env, for SB3's get_attr and
        # her.LocalGoalReward; a proxy env reads them from its worker
        if name.startswith("_") or name in ("envs", "labels"):
            raise AttributeError(name)
        env = self.__dict__.get("envs", [None])[0]
        if env is None:
            raise AttributeError(name)
        try:
            return env.get_wrapper_attr(name)
        except AttributeError:
            inner = env.unwrapped
            if hasattr(type(inner), "call") and hasattr(inner, "_worker"):
                return inner.call(name)
            raise

    def close(self) -> None:
        """Close every env."""
        for env in self.envs:
            env.close()

    def _tag(self, info: dict[str, Any]) -> dict[str, Any]:
        return {**info, "task": self.labels[self.current], "task_index": self.current}
