"""DelayAwareObservation: the last k actions and the observation's age in the observation (delayed MDPs).

With a delay between an action and its effect, the newest state alone does not say where the arm is going: the
actions still in flight do. rtgym's answer for real-time envs (an action buffer in the observation) is what this
wrapper gives a uniros env:

- ``action_history=k``: the last k actions, newest first, appended (zeros after a reset);
- ``observation_age=True``: how old the observation is, in seconds, appended: the time between the env loop
  building the returns from the newest joint state and ``step`` handing them out (the env's
  ``timing.observation_age_ns``; 0 after a reset).

On a goal env (Dict observation) only the ``observation`` key grows, so ``compute_reward`` on the goals is
unchanged. The bounds of the new entries: the action space's for the actions, [0, inf) for the age.
"""

from __future__ import annotations

import collections
from typing import Any

import gymnasium as gym
import numpy as np

from uniros_async.errors import ConfigError

__all__ = ["DelayAwareObservation"]


class DelayAwareObservation(gym.Wrapper[Any, Any, Any, Any]):
    """Append the last ``action_history`` actions and the observation's age (see the module docstring).

    Args:
        env: an env with a 1-D Box observation (or a Dict with a 1-D Box ``observation``) and a 1-D Box action.
        action_history: how many past actions to append (k >= 0).
        observation_age: append the observation's age in seconds.

    Raises:
        ConfigError: ``action_history`` is not an int >= 0, nothing to append, or the spaces are not 1-D Boxes.
    """

    def __init__(self, env: gym.Env[Any, Any], *, action_history: int = 1, observation_age: bool = True) -> None:
        super().__init__(env)
        if isinstance(action_history, bool) or not isinstance(action_history, int) or action_history < 0:
            raise ConfigError(f"DelayAwareObservation.action_history: expected an int >= 0, got {action_history!r}")
        if action_history == 0 and not observation_age:
            raise ConfigError("DelayAwareObservation: expected action_history >= 1 or observation_age=True")
        act = env.action_space
        if not isinstance(act, gym.spaces.Box) or len(act.shape) != 1:
            raise ConfigError(f"DelayAwareObservation: expected a 1-D Box action space, got {act}")
        space = env.observation_space
        self._goal = isinstance(space, gym.spaces.Dict)
        box = space["observation"] if self._goal else space  # type: ignore[index]
        if not isinstance(box, gym.spaces.Box) or len(box.shape) != 1:
            raise ConfigError(f"DelayAwareObservation: expected a 1-D Box observation, got {box}")
        self.k, self.with_age = action_history, observation_age
        self._zero = np.zeros(act.shape[0], dtype=np.float32)
        self._actions: collections.deque[np.ndarray] = collections.deque(maxlen=max(1, self.k))
        low = [box.low, np.tile(act.low, self.k)] + ([np.zeros(1)] if observation_age else [])
        high = [box.high, np.tile(act.high, self.k)] + ([np.full(1, np.inf)] if observation_age else [])
        new = gym.spaces.Box(np.concatenate(low).astype(np.float32), np.concatenate(high).astype(np.float32))
        if self._goal:
            self.observation_space = gym.spaces.Dict({**space.spaces, "observation": new})  # type: ignore[attr-defined]
        else:
            self.observation_space = new

    def _age_s(self) -> float:
        timing = getattr(self.env.unwrapped, "timing", None)
        ages = getattr(timing, "observation_age_ns", None)
        return float(ages[-1]) / 1e9 if ages else 0.0

    def _extend(self, obs: Any, age_s: float) -> Any:
        parts = [np.asarray(obs["observation"] if self._goal else obs, dtype=np.float32)]
        if self.k:
            parts.extend(list(self._actions)[: self.k])
            parts.extend([self._zero] * (self.k - len(self._actions)))
        if self.with_age:
            parts.append(np.array([age_s], dtype=np.float32))
        flat = np.concatenate(parts)
        return {**obs, "observation": flat} if self._goal else flat

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        self._actions.clear()
        info = dict(info)
        info["observation_age_s"] = 0.0
        return self._extend(obs, 0.0), info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._actions.appendleft(np.asarray(action, dtype=np.float32).reshape(self._zero.shape))
        age = self._age_s()
        info = dict(info)
        info["observation_age_s"] = age
        return self._extend(obs, age), float(reward), terminated, truncated, info
