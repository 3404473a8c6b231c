"""Wrappers for the reach envs and their kin.

- ``NormalizeObservation``: maps each finite observation bound to [-1, 1] (fixed bounds, not running
  statistics: the same policy input on sim and real arms, and nothing to carry between runs). On a goal env only
  the ``observation`` key is scaled, so ``compute_reward`` on the goals is unchanged.
- ``RescaleAction``: gymnasium's, re-exported (the envs already take actions in [-1, 1]).
- ``TimeLimit``: truncates after ``max_episode_steps`` and sets ``info["is_success"] = False`` on truncation.
- ``PadSpaces``: pads observations (with zeros) and actions to given sizes so envs of different arms share one
  policy (the paper's multi-task experiment); extra action entries are ignored. ``info["padding"]`` says how
  much was added.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.wrappers import RescaleAction

from uniros_async.errors import ConfigError

__all__ = ["NormalizeObservation", "PadSpaces", "RescaleAction", "TimeLimit"]


def _box_of(space: gym.Space[Any], where: str) -> gym.spaces.Box:
    if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
        raise ConfigError(f"{where}: expected a 1-D Box, got {space}")
    return space


class NormalizeObservation(gym.ObservationWrapper[Any, Any, Any]):
    """Scale observations from their bounds to [-1, 1] (see the module docstring)."""

    def __init__(self, env: gym.Env[Any, Any]) -> None:
        super().__init__(env)
        space = env.observation_space
        self._goal = isinstance(space, gym.spaces.Dict)
        box = _box_of(space["observation"] if self._goal else space, "NormalizeObservation")  # type: ignore[index]
        if not (np.all(np.isfinite(box.low)) and np.all(np.isfinite(box.high))):
            raise ConfigError("NormalizeObservation needs finite observation bounds")
        self._mid = ((box.high + box.low) / 2).astype(np.float32)
        self._half = np.maximum((box.high - box.low) / 2, 1e-9).astype(np.float32)
        scaled = gym.spaces.Box(-1.0, 1.0, box.shape, np.float32)
        if self._goal:
            self.observation_space = gym.spaces.Dict({**space.spaces, "observation": scaled})  # type: ignore[attr-defined]
        else:
            self.observation_space = scaled

    def observation(self, observation: Any) -> Any:
        if self._goal:
            return {**observation, "observation": self._scale(observation["observation"])}
        return self._scale(observation)

    def _scale(self, x: np.ndarray) -> np.ndarray:
        scaled: np.ndarray = np.clip((x - self._mid) / self._half, -1.0, 1.0).astype(np.float32)
        return scaled


class TimeLimit(gym.wrappers.TimeLimit):
    """gymnasium's TimeLimit that also marks a truncated episode as not successful."""

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = super().step(action)
        if truncated and not terminated:
            info = {**info, "is_success": False}
        return obs, reward, terminated, truncated, info


class PadSpaces(gym.Wrapper[Any, Any, Any, Any]):
    """Pad observation and action to ``obs_size`` / ``action_size`` (zeros in, extra actions ignored)."""

    def __init__(self, env: gym.Env[Any, Any], obs_size: int, action_size: int) -> None:
        super().__init__(env)
        self._goal = isinstance(env.observation_space, gym.spaces.Dict)
        obs_box = _box_of(env.observation_space["observation"] if self._goal else env.observation_space, "PadSpaces")  # type: ignore[index]
        act_box = _box_of(env.action_space, "PadSpaces")
        n_obs, n_act = obs_box.shape[0], act_box.shape[0]
        if obs_size < n_obs or action_size < n_act:
            raise ConfigError(
                f"PadSpaces: cannot pad {env.spec.id if env.spec else env} (observation {n_obs}, action {n_act}) "
                f"to smaller sizes (observation {obs_size}, action {action_size})"
            )
        self._n_obs, self._n_act = n_obs, n_act
        self.padding = {"observation": obs_size - n_obs, "action": action_size - n_act}
        pad_o = obs_size - n_obs
        low = np.concatenate([obs_box.low, np.zeros(pad_o, np.float32)])
        high = np.concatenate([obs_box.high, np.zeros(pad_o, np.float32)])
        padded = gym.spaces.Box(low, high, dtype=np.float32)
        if self._goal:
            self.observation_space = gym.spaces.Dict({**env.observation_space.spaces, "observation": padded})  # type: ignore[attr-defined]
        else:
            self.observation_space = padded
        pad_a = action_size - n_act
        self.action_space = gym.spaces.Box(
            np.concatenate([act_box.low, np.full(pad_a, -1.0, np.float32)]),
            np.concatenate([act_box.high, np.full(pad_a, 1.0, np.float32)]),
            dtype=np.float32,
        )

    def _pad(self, obs: Any) -> Any:
        def pad(x: np.ndarray) -> np.ndarray:
            return np.concatenate([x, np.zeros(self.padding["observation"], np.float32)]).astype(np.float32)

        return {**obs, "observation": pad(obs["observation"])} if self._goal else pad(obs)

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        return self._pad(obs), {**info, "padding": dict(self.padding)}

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        a = np.asarray(action, dtype=np.float32)
        if a.shape != self.action_space.shape:
            raise gym.error.InvalidAction(f"action must have shape {self.action_space.shape}, got {a.shape}")
        obs, reward, terminated, truncated, info = self.env.step(a[: self._n_act])
        return self._pad(obs), reward, terminated, truncated, {**info, "padding": dict(self.padding)}
