"""A reach env driven straight at its goal, for tests that only need to see an arm move where it is told, however it
is reached (a served arm, a bridged one, over tcp or tls).

Imported as ``_reach``: tests/ is on ``sys.path`` (pytest's default import mode puts the folder of tests/conftest.py
there).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

import uniros_async  # noqa: F401  (registers the ids)


def distances_toward_goal(robot: str, steps: int, **kwargs: Any) -> list[float]:
    """Make ``uniros/Rx200Reach-v0`` on ``robot``, reset it (seed 3), act ``steps`` times with the absolute joint
    targets that IK finds for its goal (fewer if the goal is reached) and close it. Returns the distance from the EE
    to the goal at the reset and after each step."""
    env = gym.make("uniros/Rx200Reach-v0", robot=robot, action_mode="absolute", **kwargs)
    try:
        obs, _ = env.reset(seed=3)
        u = env.unwrapped
        q, ok = u.kin.ik(u.goal)
        assert ok, f"goal {u.goal} unreachable"
        action = (2 * (q - u._lower) / (u._upper - u._lower) - 1).astype(np.float32)
        distances = [float(obs[6])]  # EE position (3), direction (3), distance
        for _ in range(steps):
            obs, _, terminated, _, info = env.step(action)
            distances.append(info["distance"])
            if terminated:
                break
    finally:
        env.close()
    assert np.all(np.isfinite(distances))
    return distances
