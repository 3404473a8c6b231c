"""``make``: one env in its own worker process, behind ``ProxyEnv``, a gymnasium.Env that forwards to it.

``uniros_async.make`` is not ``gymnasium.make``: the same id given to ``gymnasium.make`` builds the env in the
calling process; given to ``uniros_async.make`` it is built in a worker process, and what comes back is a proxy
(``ProxyEnv``: ``reset``, ``step``, ``call`` and ``close`` go to the worker; its ``pid`` is the worker's).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from uniros_async.errors import ConfigError
from uniros_async.runtime.envargs import PLACEMENT_KWARG, check_env_args
from uniros_async.runtime.protocol import space_from_plain
from uniros_async.runtime.ray_placement import apply_backend
from uniros_async.runtime.supervisor import Supervisor

__all__ = ["ProxyEnv", "make"]


class ProxyEnv(gym.Env[Any, Any]):
    """A gymnasium.Env whose env runs in a worker process (see ``make``)."""

    def __init__(self, supervisor: Supervisor) -> None:
        super().__init__()
        self._sup = supervisor
        self._worker = supervisor.workers[0]
        info = self._worker.info
        self.observation_space = space_from_plain(info["observation_space"])
        self.action_space = space_from_plain(info["action_space"])
        self.metadata = {**self.metadata, **info.get("metadata", {})}
        self.env_id = self._worker.spec.env_id
        self.pid = self._worker.process.pid
        self._closed = False

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        """Reset the env in the worker. Raises WorkerError on any failure there."""
        super().reset(seed=seed)
        self._check_open()
        obs, info = self._sup.call(
            self._worker.request({"op": "reset", "seed": seed, "options": options}, self._sup.call_timeout_s)
        )
        return obs, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """Step the env in the worker. Raises WorkerError on any failure there (a bad action included)."""
        self._check_open()
        obs, reward, terminated, truncated, info = self._sup.call(
            self._worker.request({"op": "step", "action": np.asarray(action)}, self._sup.call_timeout_s)
        )
        return obs, reward, terminated, truncated, info

    def call(self, name: str, *args: Any, **kwargs: Any) -> Any:
        """Call the env's method ``name`` (or read its attribute) in the worker; plain data in and out."""
        self._check_open()
        msg = {"op": "call", "name": name, "args": list(args), "kwargs": kwargs}
        return self._sup.call(self._worker.request(msg, self._sup.call_timeout_s))

    def close(self) -> None:
        """Close the env and stop the worker; idempotent, bounded in time."""
        if self._closed:
            return
        self._closed = True
        self._sup.close()

    def _check_open(self) -> None:
        if self._closed:
            raise gym.error.ClosedEnvironmentError(f"the proxy of {self.env_id} is closed; make a new one")

    def __repr__(self) -> str:
        return f"<ProxyEnv {self.env_id} pid={self.pid}>"


def make(
    env_id: str,
    *,
    in_process: bool = False,
    start_timeout_s: float = 60.0,
    call_timeout_s: float = 60.0,
    transport: str = "shm",
    backend: str = "local",
    **kwargs: Any,
) -> gym.Env[Any, Any]:
    """Make ``env_id`` in its own worker process and return a gymnasium.Env proxy for it (``ProxyEnv``).

    Unlike ``gymnasium.make``, which builds the env in this process, the env runs in a worker process with its own
    event loop; ``in_process=True`` returns ``gymnasium.make``'s env instead. Several envs at once: ``make_vec``.

    Args:
        env_id: a registered id, e.g. ``"uniros/Rx200Reach-v0"``, or ``"module:Id"`` for an env of your own
            (``module`` registers ``Id``; the worker, a fresh interpreter, imports it too).
        in_process: return the plain ``gymnasium.make`` env instead (for debugging).
        start_timeout_s: bound on starting the worker and building the env.
        call_timeout_s: bound on each reset/step.
        transport: how the agent side talks to the worker: ``"shm"`` (default) or ``"tcp"`` (loopback).
        backend: ``"local"`` (the default) or ``"ray"``: the worker is placed by Ray (see ``make_vec``).
        **kwargs: passed to ``gymnasium.make`` in the worker (clock, robot, reward_type, ...), except ``worker``:
            where the worker runs, None (here) or a Ray placement, ``"ray"`` or ``{"ray": {...}}`` (see
            ``make_vec`` and runtime/ray_backend.py).

    Raises:
        ConfigError: an unknown id or keyword argument, or a ``worker`` that is neither None nor a Ray placement
            (raised here, before any process starts).
        WorkerError: the worker failed to start or to build the env (its traceback attached), or Ray could not
            place or start it.
    """
    ((env_id, kwargs),) = apply_backend([(env_id, kwargs)], "local" if in_process else backend)
    check_env_args(env_id, kwargs)
    if in_process:
        if kwargs.get(PLACEMENT_KWARG) is not None:
            raise ConfigError("in_process=True and worker=... exclude each other")
        kwargs = {k: v for k, v in kwargs.items() if k != PLACEMENT_KWARG}
        return gym.make(env_id, **kwargs)
    sup = Supervisor(
        [(env_id, kwargs)], start_timeout_s=start_timeout_s, call_timeout_s=call_timeout_s, transport=transport
    )
    try:
        return ProxyEnv(sup)
    except BaseException:
        sup.close()
        raise
