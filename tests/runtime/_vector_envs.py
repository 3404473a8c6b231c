"""Envs of gymnasium's own vector-env tests, registered when this module is imported, so that ``make_vec`` can make
them in its workers as ``"_vector_envs:Id"``.

Adapted from Gymnasium's tests/testing_env.py and tests/vector/ (``GenericTestEnv``, the count and debug step
functions; https://github.com/Farama-Foundation/Gymnasium, MIT License, Copyright (c) 2016 OpenAI, (c) 2022
Farama Foundation). Changed: the envs are made by id in a worker process (not by a thunk in the caller), so their
step and reset functions are module-level functions that pickle by name.
"""

from __future__ import annotations

import types
from collections.abc import Callable
from typing import Any

import gymnasium as gym
from gymnasium import spaces

GENERIC = "_vector_envs:UnirosGenericTestEnv-v0"


# ---------------------------------------------------------------- Gymnasium: tests/testing_env.py


def basic_reset_func(self: Any, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
    """A reset that samples the observation space."""
    super(GenericTestEnv, self).reset(seed=seed)
    self.observation_space.seed(self.np_random_seed)
    return self.observation_space.sample(), {"options": options}


def basic_step_func(self: Any, action: Any) -> Any:
    """A step that samples the observation space."""
    return self.observation_space.sample(), 0, False, False, {}


def basic_render_func(self: Any) -> None:
    """Renders nothing."""


class GenericTestEnv(gym.Env[Any, Any]):
    """A generic testing environment whose reset, step and render are the functions given."""

    def __init__(
        self,
        action_space: spaces.Space[Any] | None = None,
        observation_space: spaces.Space[Any] | None = None,
        reset_func: Callable[..., Any] = basic_reset_func,
        step_func: Callable[..., Any] = basic_step_func,
        render_func: Callable[..., Any] = basic_render_func,
        metadata: dict[str, Any] | None = None,
        render_mode: str | None = None,
    ) -> None:
        self.action_space = spaces.Box(0, 1, (1,)) if action_space is None else action_space
        self.observation_space = spaces.Box(0, 1, (1,)) if observation_space is None else observation_space
        self.reset = types.MethodType(reset_func, self)  # type: ignore[method-assign]
        self.step = types.MethodType(step_func, self)  # type: ignore[method-assign]
        self.render = types.MethodType(render_func, self)  # type: ignore[method-assign]
        self.metadata = {"render_modes": []} if metadata is None else metadata
        self.render_mode = render_mode


# ---------------------------------------------------------------- Gymnasium: tests/vector/


def debug_step_func(self: Any, action: Any) -> Any:
    """A step that checks its action is in the action space (so a value that crossed the wire must be one)."""
    assert action in self.action_space, (action, self.action_space)
    return self.observation_space.sample(), 0, False, False, {}


def count_reset(self: Any, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
    """Resets the count to the seed (0 without one)."""
    super(GenericTestEnv, self).reset(seed=seed)
    self.count = seed if seed is not None else 0
    return self.count, {}


def count_step(self: Any, action: Any) -> Any:
    """Counts steps; the reward is the action; terminates at ``max_count``."""
    self.count += 1
    return self.count, action, self.count == self.max_count, False, {}


def final_obs_reset(self: Any, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
    """test_final_obs_info's reset."""
    return 0, {"reset": True}


def final_obs_step(self: Any, action: Any) -> Any:
    """test_final_obs_info's step."""
    return (action if action < 3 else 0, 0, action >= 3, False, {"action": action})


for _id, _entry in [
    (GENERIC, GenericTestEnv),
]:
    _name = _id.partition(":")[2]
    if _name not in gym.registry:
        gym.register(_name, entry_point=_entry, disable_env_checker=True, order_enforce=False)
