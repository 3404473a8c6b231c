"""A user's own env, registered when this module is imported: what ``make``/``make_vec`` take as
``"_custom_env:UnirosTestMarkedCartPole-v0"`` (gymnasium's "module:Id"), importing it in the caller and in the
worker."""

from __future__ import annotations

import gc
import os
from typing import Any

import gymnasium as gym
from gymnasium.envs.classic_control.cartpole import CartPoleEnv

ENV_ID = "UnirosTestMarkedCartPole-v0"


class MarkedCartPole(CartPoleEnv):
    """CartPole whose step says which process stepped it."""

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = super().step(action)
        return obs, reward, terminated, truncated, {**info, "stepped_by_pid": os.getpid()}

    def gc_state(self) -> list[int]:
        """The cyclic collector's view of this process: objects frozen out of its reach, objects it walks."""
        return [gc.get_freeze_count(), len(gc.get_objects())]


if ENV_ID not in gym.registry:
    gym.register(ENV_ID, entry_point=MarkedCartPole, max_episode_steps=50)
