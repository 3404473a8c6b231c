"""``make_vec([id] * 2)`` for every env id gymnasium registers, each compared with gymnasium's SyncVectorEnv of the
same id in the same test (seeded reset, then three steps of the same actions: observations, rewards, flags and infos
must be equal).

An id is skipped, with the reason, only when gymnasium itself cannot make it here for want of a package this
project does not install (box2d, jax, shimmy, mujoco-py for the v2/v3 MuJoCo envs, mujoco<3 for Pusher-v4): then
AsyncVectorEnv cannot vectorize it either. Every other id must work.
"""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import data_equivalence
from gymnasium.vector import SyncVectorEnv

from uniros_async.runtime import make_vec

pytestmark = pytest.mark.slow

GYMNASIUM_IDS = sorted(
    env_id
    for env_id, spec in gym.registry.items()
    if isinstance(spec.entry_point, str) and spec.entry_point.startswith("gymnasium.")
)


def _makeable_here(env_id: str) -> None:
    """Skip, naming what is missing, when gymnasium cannot make ``env_id`` here for want of a package."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            gym.make(env_id).close()
    except (ImportError, gym.error.DependencyNotInstalled) as exc:
        pytest.skip(f"{env_id} needs a package not installed here: {type(exc).__name__}: {str(exc)[:160]}")


@pytest.mark.parametrize("env_id", GYMNASIUM_IDS)
def test_make_vec_matches_sync_vector_env_for_every_gymnasium_id(env_id: str) -> None:
    _makeable_here(env_id)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the reference's own env checker and deprecation notes
        sync = SyncVectorEnv([lambda: gym.make(env_id) for _ in range(2)])
    venv = make_vec([env_id] * 2)
    try:
        assert venv.single_observation_space == sync.single_observation_space
        assert venv.single_action_space == sync.single_action_space
        obs, info = venv.reset(seed=0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref_obs, ref_info = sync.reset(seed=0)
            assert data_equivalence(obs, ref_obs) and data_equivalence(info, ref_info)
            venv.action_space.seed(0)
            for _ in range(3):
                actions = venv.action_space.sample()
                got = venv.step(actions)
                ref = sync.step(actions)
                for a, b in zip(got, ref, strict=True):
                    assert data_equivalence(a, b), (env_id, a, b)
        assert obs in venv.observation_space and np.all(venv.pids)
    finally:
        venv.close()
        sync.close()
