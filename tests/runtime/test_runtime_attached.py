"""The attached mode the workers use (an env on its owner's event loop, stepped through ``astep_through``) behaves
exactly as the synchronous gymnasium path, wrappers included."""

from __future__ import annotations

import asyncio
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import uniros_async  # noqa: F401  (registers the ids)
from uniros_async.envs.runtime import deferred_start
from uniros_async.envs.wrappers import PadSpaces
from uniros_async.runtime.attached import areset_through, astep_through, supports_async

pytestmark = pytest.mark.slow

KW: dict[str, Any] = {"turn_based": True, "max_episode_steps": 4}


def _actions(n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(1)
    return [rng.uniform(-1, 1, 6).astype(np.float32) for _ in range(n)]


def _same(a: Any, b: Any) -> None:
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), (a, b)
        for k in a:
            _same(a[k], b[k])
    elif isinstance(a, tuple | list):
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            _same(x, y)
    else:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_attached_env_steps_exactly_like_the_synchronous_one() -> None:
    actions = _actions(6)  # 4 steps to the time limit, then two more (gymnasium's TimeLimit does not stop them)
    sync = PadSpaces(gym.make("uniros/Rx200Reach-v0", **KW), 32, 6)
    try:
        expected: list[Any] = [sync.reset(seed=3)]
        expected += [sync.step(a) for a in actions]
    finally:
        sync.close()

    async def attached() -> list[Any]:
        with deferred_start():
            env = PadSpaces(gym.make("uniros/Rx200Reach-v0", **KW), 32, 6)
        assert supports_async(env) and env.unwrapped.attached
        await env.unwrapped.astart()
        try:
            with pytest.raises(gym.error.ResetNeeded):
                await astep_through(env, actions[0])
            out: list[Any] = [await areset_through(env, 3, None)]
            out += [await astep_through(env, a) for a in actions]
            with pytest.raises(gym.error.InvalidAction, match="shape"):
                await astep_through(env, np.zeros(3, np.float32))
            with pytest.raises(gym.error.InvalidAction, match="outside the action space"):
                await astep_through(env, np.full(6, 3.0, np.float32))  # the arm holds; the env stays usable
            await astep_through(env, actions[0])
            with pytest.raises(RuntimeError, match="attached"):
                env.step(actions[0])  # the synchronous API of an attached env refuses, it cannot block its own loop
        finally:
            await env.unwrapped.aclose()
            await env.unwrapped.aclose()  # idempotent
        with pytest.raises(gym.error.ClosedEnvironmentError):
            await env.unwrapped.astep(actions[0])
        return out

    got = asyncio.run(attached())
    assert [r[3] for r in got[1:]] == [False, False, False, True, True, True]  # truncated from the 4th step
    _same(expected, got)


def test_unknown_wrappers_fall_back_to_the_loop_thread() -> None:
    with deferred_start():
        env = gym.wrappers.ClipAction(gym.make("uniros/Rx200Reach-v0", **KW))
    try:
        assert not supports_async(env)
        env.unwrapped.start_thread()
        env.reset(seed=0)
        obs, *_ = env.step(np.zeros(5, np.float32))
        assert obs.shape == (28,)
    finally:
        env.close()
