"""Cheap envs whose observations are what other pipelines carry, for ``uniros bench throughput``: a goal env's Dict
observation and an Atari-style 84x84x3 uint8 frame. Their steps cost next to nothing, so a vector env's time per
step is what moving their observations costs. Registered on import, as ``"uniros_async.bench.envs:Id"``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

__all__ = ["DICT_ID", "IMAGE_ID", "DictObsEnv", "ImageObsEnv", "make_env"]

DICT_ID = "uniros_async.bench.envs:UnirosBenchDictObs-v0"
IMAGE_ID = "uniros_async.bench.envs:UnirosBenchImageObs-v0"
EPISODE_STEPS = 200


class DictObsEnv(gym.Env[Any, Any]):
    """A goal env's observation (``observation``, ``achieved_goal``, ``desired_goal``; float64, as the uniros goal
    envs have it), four discrete actions that move the achieved goal; episodes of ``EPISODE_STEPS``."""

    def __init__(self) -> None:
        box = spaces.Box(-10.0, 10.0, (3,), np.float64)
        obs_space = spaces.Dict(
            {"observation": spaces.Box(-10.0, 10.0, (10,), np.float64), "achieved_goal": box, "desired_goal": box}
        )
        self.observation_space = obs_space
        self.action_space = spaces.Discrete(4)
        self._t = 0
        self._obs = {k: np.zeros(s.shape or (), s.dtype) for k, s in obs_space.spaces.items()}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        super().reset(seed=seed)
        self._t = 0
        self._obs["desired_goal"][:] = self.np_random.uniform(-1.0, 1.0, 3)
        self._obs["achieved_goal"][:] = 0.0
        return {k: v.copy() for k, v in self._obs.items()}, {}

    def step(self, action: Any) -> Any:
        self._t += 1
        a = int(action)
        self._obs["achieved_goal"][a % 3] += 0.01 if a < 3 else -0.01
        self._obs["observation"][:3] = self._obs["achieved_goal"]
        distance = float(np.linalg.norm(self._obs["achieved_goal"] - self._obs["desired_goal"]))
        obs = {k: v.copy() for k, v in self._obs.items()}
        return obs, -distance, False, self._t >= EPISODE_STEPS, {"distance": distance}


class ImageObsEnv(gym.Env[Any, Any]):
    """An 84x84x3 uint8 frame per step (the frame an Atari pipeline's agent sees), four discrete actions; episodes
    of ``EPISODE_STEPS``. Each step changes one row of the frame, so no step returns the same bytes."""

    def __init__(self) -> None:
        self.observation_space = spaces.Box(0, 255, (84, 84, 3), np.uint8)
        self.action_space = spaces.Discrete(4)
        self._t = 0
        self._frame = np.zeros((84, 84, 3), np.uint8)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> Any:
        super().reset(seed=seed)
        self._t = 0
        self._frame[:] = self.np_random.integers(0, 256, self._frame.shape, dtype=np.uint8)
        return self._frame.copy(), {}

    def step(self, action: Any) -> Any:
        self._t += 1
        self._frame[self._t % 84] = int(action) * 60
        return self._frame.copy(), 1.0, False, self._t >= EPISODE_STEPS, {}


if DICT_ID.partition(":")[2] not in gym.registry:
    gym.register(DICT_ID.partition(":")[2], entry_point="uniros_async.bench.envs:DictObsEnv")
if IMAGE_ID.partition(":")[2] not in gym.registry:
    gym.register(IMAGE_ID.partition(":")[2], entry_point="uniros_async.bench.envs:ImageObsEnv")


def make_env(env_id: str, kwargs: dict[str, Any]) -> Any:
    """``gymnasium.make(env_id, **kwargs)`` for the benches: the uniros ids are registered first (also in a process
    spawned to call this), and this module's by its import."""
    if env_id.startswith("uniros/"):
        import uniros_async  # noqa: F401  (registers the uniros ids)

    return gym.make(env_id, **kwargs)
