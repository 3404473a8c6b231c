"""HER's reward relabelling in the agent's process.

SB3's HerReplayBuffer computes the reward of every relabelled transition by asking the env:
``env.env_method("compute_reward", achieved, desired, infos, indices=[0])`` on each ``sample``. With envs in
worker processes that is a round trip per gradient update, queued behind the env's step; with AsyncTD3's learner
thread it would also race the actor's step on the same worker connection. ``LocalGoalReward`` answers that call
here with a pure function of the arguments and the env's reward settings, read once from each env at wrap time,
and forwards everything else to the wrapped VecEnv.

For the reach tasks the function is ``tasks.reach.reach_reward``, the very arithmetic ``ReachEnv.batch_reward``
delegates to, so the two cannot drift.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecEnvWrapper

from uniros_async.errors import ConfigError

__all__ = ["LocalGoalReward", "RewardFn", "computes_reward_locally"]

RewardFn = Callable[..., np.ndarray]
"""``reward_fn(achieved_goal, desired_goal, info, **settings) -> rewards``, pure (no env state)."""

REACH_SETTINGS = ("reward_type", "reach_tolerance")


class LocalGoalReward(VecEnvWrapper):
    """A VecEnv wrapper that computes ``env_method("compute_reward", ...)`` locally; see the module docstring.

    Args:
        venv: the VecEnv (e.g. ``uniros_async.make_vec([...]).as_sb3()``, or SB3's own).
        reward_fn: the pure reward; default ``tasks.reach.reach_reward``.
        settings: names of the env attributes passed to ``reward_fn`` as keyword arguments, read from every
            sub-env with ``get_attr`` now (a later ``set_attr`` of one of them through this wrapper updates them).
        terminated_fn: if given, ``env_method("compute_terminated", ...)`` is answered locally the same way;
            otherwise it is forwarded (SB3 does not call it).

    Raises:
        ConfigError: a sub-env lacks one of ``settings`` (the default suits the uniros reach tasks only; pass
            ``reward_fn`` and ``settings`` for another task).
    """

    def __init__(
        self,
        venv: VecEnv,
        reward_fn: RewardFn | None = None,
        settings: Sequence[str] = REACH_SETTINGS,
        terminated_fn: RewardFn | None = None,
    ) -> None:
        super().__init__(venv)
        if reward_fn is None:
            from uniros_async.tasks.reach import reach_reward

            reward_fn = reach_reward
        self.reward_fn: RewardFn = reward_fn
        self.terminated_fn = terminated_fn
        self.setting_names = tuple(settings)
        self.settings: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for name in self.setting_names:
            try:
                values = venv.get_attr(name)
            except AttributeError as exc:
                raise ConfigError(
                    f"LocalGoalReward needs the env attribute {name!r} (settings={self.setting_names}) to compute "
                    f"rewards locally, and the env has none: {exc}. Pass reward_fn= and settings= for this task"
                ) from exc
            for i, value in enumerate(values):
                self.settings[i][name] = value

    def reset(self) -> Any:
        return self.venv.reset()

    def step_wait(self) -> Any:
        return self.venv.step_wait()

    def env_method(self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any) -> list[Any]:
        """``compute_reward`` (and ``compute_terminated`` with ``terminated_fn``) here, one result per index;
        anything else in the envs."""
        local: dict[str, RewardFn | None] = {"compute_reward": self.reward_fn, "compute_terminated": self.terminated_fn}
        fn = local.get(method_name)
        if fn is None:
            return self.venv.env_method(method_name, *method_args, indices=indices, **method_kwargs)
        return [fn(*method_args, **method_kwargs, **self.settings[i]) for i in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        """Set it in the envs (and here, if it is one of the reward settings)."""
        self.venv.set_attr(attr_name, value, indices)
        if attr_name in self.setting_names:
            for i in self._get_indices(indices):
                self.settings[i][attr_name] = value

    def _get_indices(self, indices: Any) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        if isinstance(indices, int | np.integer):
            return [int(indices)]
        return [int(i) for i in indices]


def computes_reward_locally(venv: VecEnv) -> bool:
    """Whether ``venv.env_method("compute_reward", ...)`` runs in this process without crossing to a worker:
    a ``LocalGoalReward`` somewhere in the wrapper chain, or SB3's DummyVecEnv at its bottom over envs that are
    not worker proxies (``uniros_async.make``'s ProxyEnv, or an env holding them in ``.envs`` such as
    ``training.multitask.TaskSamplerEnv`` with ``placement: workers``)."""
    from uniros_async.runtime.proxy import ProxyEnv

    env: Any = venv
    while True:
        if isinstance(env, LocalGoalReward):
            return True
        if isinstance(env, DummyVecEnv):
            for e in env.envs:
                inner = [e.unwrapped, *getattr(e.unwrapped, "envs", [])]
                if any(isinstance(getattr(x, "unwrapped", x), ProxyEnv) for x in inner):
                    return False
            return True
        if not isinstance(env, VecEnvWrapper):
            return False
        env = env.venv
