"""Envs of stable-baselines3's own VecEnv tests, registered when this module is imported, so that ``make_vec`` can
make them in its workers as ``"_sb3_envs:Id"``.

Adapted from stable-baselines3's tests/test_vec_envs.py (``CustomGymEnv``, ``StepEnv``;
https://github.com/DLR-RM/stable-baselines3, MIT License, Copyright (c) 2019 Antonin Raffin). Changed: the envs are
made by id in a worker process (not by a thunk in the caller); the Monitor-wrapped one has an entry point of its
own.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.monitor import Monitor

CUSTOM = "_sb3_envs:UnirosSb3CustomEnv-v0"
MONITORED = "_sb3_envs:UnirosSb3MonitoredCustomEnv-v0"
STEP = "_sb3_envs:UnirosSb3StepEnv-v0"


class CustomGymEnv(gym.Env[Any, Any]):
    """SB3's custom env for testing: observations sampled from ``space``, episodes of 4 steps."""

    def __init__(self, space: spaces.Space[Any], render_mode: str = "rgb_array") -> None:
        self.action_space = space
        self.observation_space = space
        self.current_step = 0
        self.ep_length = 4
        self.render_mode = render_mode
        self.current_options: dict[str, Any] | None = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        if seed is not None:
            self.seed(seed)
        self.current_step = 0
        self.current_options = options
        self._choose_next_state()
        return self.state, {}

    def step(self, action: Any) -> Any:
        reward = float(np.random.rand())
        self._choose_next_state()
        self.current_step += 1
        terminated = False
        truncated = self.current_step >= self.ep_length
        return self.state, reward, terminated, truncated, {}

    def _choose_next_state(self) -> None:
        self.state = self.observation_space.sample()

    def render(self) -> Any:
        if self.render_mode == "rgb_array":
            return np.zeros((4, 4, 3))
        return None

    def seed(self, seed: int | None = None) -> None:
        if seed is not None:
            np.random.seed(seed)
            self.observation_space.seed(seed)

    @staticmethod
    def custom_method(dim_0: int = 1, dim_1: int = 1) -> np.ndarray:
        """A method for env_method to call."""
        return np.ones((dim_0, dim_1))


def monitored_custom_env(space: spaces.Space[Any]) -> gym.Env[Any, Any]:
    """CustomGymEnv under SB3's Monitor (what env_is_wrapped and get_attr through wrappers are tested with)."""
    return Monitor(CustomGymEnv(space))


class StepEnv(gym.Env[Any, Any]):
    """An env whose observation is the step count, truncated after ``max_steps`` (for terminal observations)."""

    def __init__(self, max_steps: int) -> None:
        self.action_space = spaces.Discrete(2)
        self.observation_space = spaces.Box(np.array([0]), np.array([999]), dtype="int")
        self.max_steps = max_steps
        self.current_step = 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        self.current_step = 0
        return np.array([self.current_step], dtype="int"), {}

    def step(self, action: Any) -> Any:
        prev_step = self.current_step
        self.current_step += 1
        terminated = False
        truncated = self.current_step >= self.max_steps
        return np.array([prev_step], dtype="int"), 0.0, terminated, truncated, {}


for _id, _entry in [(CUSTOM, CustomGymEnv), (MONITORED, monitored_custom_env), (STEP, StepEnv)]:
    _name = _id.partition(":")[2]
    if _name not in gym.registry:
        gym.register(_name, entry_point=_entry, disable_env_checker=True, order_enforce=False)
