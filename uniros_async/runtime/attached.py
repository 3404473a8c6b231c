"""Stepping an attached uniros env through the wrappers gymnasium and ``make_vec`` put around it, on its owner's event
loop: ``supports_async`` says whether a wrapper stack is one of those (OrderEnforcing, TimeLimit, PadSpaces around a
uniros ``BaseEnv`` in attached mode), and ``astep_through`` / ``areset_through`` apply each wrapper with gymnasium's
semantics and await the base env's ``astep`` / ``areset``. A worker steps its env this way (runtime/worker.py): no loop
thread and no hand-over between threads; any other stack runs on a loop thread through its synchronous API.
"""

from __future__ import annotations

import sys
from typing import Any

import gymnasium as gym
import numpy as np

__all__ = ["areset_through", "astep_through", "base_env_class", "supports_async"]


def _async_wrappers() -> tuple[type, ...]:
    from uniros_async.envs import wrappers as uw

    return (gym.wrappers.OrderEnforcing, gym.wrappers.TimeLimit, uw.TimeLimit, uw.PadSpaces)


def base_env_class() -> Any:
    """uniros's ``BaseEnv`` if this process has loaded it, else None: then no env here is one. A worker of another
    gymnasium env (CartPole) thus never imports it, nor the pydantic configs it brings."""
    module = sys.modules.get("uniros_async.envs.base")
    return getattr(module, "BaseEnv", None)


def supports_async(env: gym.Env[Any, Any]) -> bool:
    """Whether ``env`` is an attached uniros BaseEnv under wrappers that ``astep_through`` knows (exact types)."""
    BaseEnv = base_env_class()  # noqa: N806
    if BaseEnv is None:
        return False
    known = _async_wrappers()
    e: Any = env
    while isinstance(e, gym.Wrapper):
        if type(e) not in known:
            return False
        e = e.env
    return isinstance(e, BaseEnv) and e.attached and type(e).step is BaseEnv.step and type(e).reset is BaseEnv.reset


async def astep_through(env: Any, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
    """``env.step(action)`` for a stack ``supports_async`` accepted, awaiting the base env's ``astep``."""
    from uniros_async.envs import wrappers as uw

    t = type(env)
    if t is uw.PadSpaces:
        a = np.asarray(action, dtype=np.float32)
        if a.shape != env.action_space.shape:
            raise gym.error.InvalidAction(f"action must have shape {env.action_space.shape}, got {a.shape}")
        obs, reward, terminated, truncated, info = await astep_through(env.env, a[: env._n_act])
        return env._pad(obs), reward, terminated, truncated, {**info, "padding": dict(env.padding)}
    if t is gym.wrappers.OrderEnforcing:
        if not env._has_reset:
            raise gym.error.ResetNeeded("Cannot call env.step() before calling env.reset()")
        return await astep_through(env.env, action)
    if t is gym.wrappers.TimeLimit or t is uw.TimeLimit:
        obs, reward, terminated, truncated, info = await astep_through(env.env, action)
        env._elapsed_steps += 1
        if env._elapsed_steps >= env._max_episode_steps:
            truncated = True
        if t is uw.TimeLimit and truncated and not terminated:
            info = {**info, "is_success": False}
        return obs, reward, terminated, truncated, info
    return await env.astep(action)  # type: ignore[no-any-return]


async def areset_through(env: Any, seed: int | None, options: dict[str, Any] | None) -> tuple[Any, dict[str, Any]]:
    """``env.reset(seed=seed, options=options)`` for a stack ``supports_async`` accepted."""
    from uniros_async.envs import wrappers as uw

    t = type(env)
    if t is uw.PadSpaces:
        obs, info = await areset_through(env.env, seed, options)
        return env._pad(obs), {**info, "padding": dict(env.padding)}
    if t is gym.wrappers.OrderEnforcing:
        env._has_reset = True
        return await areset_through(env.env, seed, options)
    if t is gym.wrappers.TimeLimit or t is uw.TimeLimit:
        env._elapsed_steps = 0
        return await areset_through(env.env, seed, options)
    return await env.areset(seed=seed, options=options)  # type: ignore[no-any-return]
