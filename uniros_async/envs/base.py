"""BaseEnv and GoalEnv: the gymnasium surface (step, reset, close, seeding) over an env loop in the background.

BaseEnv owns the protocol: it validates actions in the caller's thread (a bad action never reaches the arm: the
arm is told to hold, a gymnasium-style error is raised, and the env stays usable), refuses ``step`` before
``reset`` and after ``close``, and hands ``_astep`` / ``_areset`` to the loop thread under timeouts. What the
loop does is RobotEnv's business; what the numbers mean is TaskEnv's.

Attached mode (envs/runtime.py): an env made inside ``deferred_start()`` starts no thread; its owner runs it on
its own event loop with ``await astart()``, ``await astep(a)``, ``await areset(seed=..., options=...)`` and
``await aclose()``, with the same checks, errors and timeouts as ``step`` / ``reset`` / ``close``. The worker
processes of ``make_vec`` do this. The synchronous ``step`` / ``reset`` of an attached env raise RuntimeError.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import error as gym_error

from uniros_async.envs.config import EnvConfig
from uniros_async.envs.runtime import LoopTask, LoopThread, start_is_deferred

__all__ = ["BaseEnv", "GoalEnv"]


class BaseEnv(gym.Env[Any, np.ndarray], abc.ABC):
    """A gymnasium.Env whose world runs on its own (see the module docstring)."""

    metadata: dict[str, Any] = {"render_modes": ["rgb_array"]}

    def __init__(self, config: EnvConfig) -> None:
        super().__init__()
        self.config = config
        self._rt: LoopThread | None = None
        self._task_rt: LoopTask | None = None  # the attached mode
        self._deferred: tuple[Callable[..., Any], str, float] | None = None
        self._closed = False
        self._needs_reset = True
        self._action_bounds: tuple[Any, list[float], list[float], bool] | None = None  # (space, low, high, finite)

    # ---- lifecycle

    def _start_runtime(self, main: Callable[..., Any], name: str, timeout_s: float) -> None:
        if start_is_deferred():
            self._deferred = (main, name, timeout_s)  # started by astart() on the owner's loop
            return
        self._rt = LoopThread(main, name=name)
        self._rt.start(timeout_s)

    @property
    def attached(self) -> bool:
        """True when the env runs on its owner's event loop (made inside ``deferred_start()``)."""
        return self._deferred is not None

    async def astart(self) -> None:
        """Start the env's world (bus, sim, env loop) on the running event loop (attached mode only).

        Raises:
            RuntimeError: the env was not made inside ``deferred_start()``, or was started already.
            TimeoutError, Exception: as the synchronous start (the world failed to come up; it is closed again).
        """
        if self._deferred is None or self._task_rt is not None:
            raise RuntimeError(f"{type(self).__name__}: astart() needs an env made inside deferred_start(), once")
        main, name, timeout_s = self._deferred
        self._task_rt = LoopTask(main, name=name)
        await self._task_rt.start(timeout_s)

    def start_thread(self) -> None:
        """Start an env made inside ``deferred_start()`` on a loop thread after all (the synchronous API)."""
        if self._deferred is None or self._task_rt is not None or self._rt is not None:
            raise RuntimeError(f"{type(self).__name__}: start_thread() needs an env made inside deferred_start(), once")
        main, name, timeout_s = self._deferred
        self._deferred = None
        self._rt = LoopThread(main, name=name)
        self._rt.start(timeout_s)

    def _call(self, coro: Any, timeout_s: float) -> Any:
        if self._rt is None:
            coro.close()
            if self._deferred is not None or self._task_rt is not None:
                raise RuntimeError(
                    f"{type(self).__name__} runs attached to an event loop: use await astep() / areset() / aclose()"
                )
            raise RuntimeError(f"{type(self).__name__}: its world was never started")
        self._raise_failure(coro)
        try:
            return self._rt.call(coro, timeout_s)
        except RuntimeError:
            self._raise_failure()
            raise

    def _raise_failure(self, coro: Any = None) -> None:
        """Raise what stopped the env's world, if it stopped (closing ``coro``, which will never run); a loop
        that died with an exception is reported as that exception, not as the RuntimeError of a dead loop."""
        failure = self._rt_failure()
        if failure is None:
            return
        if coro is None:  # called while handling the dead loop's RuntimeError: report the cause alone
            raise failure from None
        coro.close()
        raise failure

    async def _acall(self, coro: Any, timeout_s: float) -> Any:
        rt = self._task_rt
        if rt is None:
            coro.close()
            raise RuntimeError(f"{type(self).__name__}: call await astart() first")
        self._raise_failure(coro)
        try:
            return await rt.call(coro, timeout_s)
        except RuntimeError:
            self._raise_failure()
            raise

    def _rt_failure(self) -> BaseException | None:
        rt = self._rt or self._task_rt
        if rt is None or rt.alive:
            return None
        return rt.failure() or RuntimeError("the env loop stopped")

    def _check_open(self) -> None:
        if self._closed:
            raise gym_error.ClosedEnvironmentError(f"{type(self).__name__} is closed; make a new one")

    # ---- gymnasium API

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """Hand ``action`` to the env loop and return, at the end of the action cycle, the newest returns.

        Raises:
            gymnasium.error.ResetNeeded: before the first ``reset``.
            gymnasium.error.ClosedEnvironmentError: after ``close``.
            gymnasium.error.InvalidAction: wrong shape, NaN, or outside the action space (the arm holds).
            RobotError: the robot stopped publishing (the arm is told to hold).
        """
        self._check_open()
        if self._needs_reset:
            raise gym_error.ResetNeeded("call reset() before step()")
        try:
            a = self._validate_action(action)
        except gym_error.InvalidAction:
            self._call(self._ahold(), self.config.step_timeout_s)
            raise
        return self._call(self._astep(a), self.config.action_cycle_s + self.config.step_timeout_s)  # type: ignore[no-any-return]

    async def astep(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """``step`` of an attached env, awaited on its owner's loop (same checks, errors and timeout)."""
        self._check_open()
        if self._needs_reset:
            raise gym_error.ResetNeeded("call reset() before step()")
        try:
            a = self._validate_action(action)
        except gym_error.InvalidAction:
            await self._acall(self._ahold(), self.config.step_timeout_s)
            raise
        return await self._acall(self._astep(a), self.config.action_cycle_s + self.config.step_timeout_s)  # type: ignore[no-any-return]

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        """Stop the arm, move it home, sample a goal, wait until settled; return the first observation."""
        super().reset(seed=seed)
        self._check_open()
        obs, info = self._call(self._areset(options or {}), self.config.reset_timeout_s + self.config.step_timeout_s)
        self._needs_reset = False
        return obs, info

    async def areset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """``reset`` of an attached env, awaited on its owner's loop (same seeding, checks and timeout)."""
        gym.Env.reset(self, seed=seed)
        self._check_open()
        timeout_s = self.config.reset_timeout_s + self.config.step_timeout_s
        obs, info = await self._acall(self._areset(options or {}), timeout_s)
        self._needs_reset = False
        return obs, info

    def close(self) -> None:
        """Stop the env loop and everything it started (sim, processes, connections); idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._rt is not None:
            self._rt.close(15.0)
        if self._task_rt is not None:
            self._task_rt.close()  # cancels the world's task; aclose() also waits for it

    async def aclose(self) -> None:
        """``close`` of an attached env: stop its world and wait (bounded) until everything it opened is closed."""
        if self._closed:
            return
        self._closed = True
        if self._task_rt is not None:
            await self._task_rt.aclose(15.0)
        if self._rt is not None:
            self._rt.close(15.0)

    def __del__(self) -> None:
        # a forgotten close() must not leave a thread driving an arm
        if not getattr(self, "_closed", True):
            self.close()

    # ---- checks

    def _validate_action(self, action: Any) -> np.ndarray:
        space = self.action_space
        assert isinstance(space, gym.spaces.Box)
        try:
            a = np.asarray(action, dtype=np.float32)
        except (TypeError, ValueError) as exc:
            raise gym_error.InvalidAction(f"action must be numbers of shape {space.shape}, got {action!r:.80}") from exc
        if a.shape != space.shape:
            raise gym_error.InvalidAction(f"action must have shape {space.shape}, got {a.shape}")
        bounds = self._action_bounds
        if bounds is None or bounds[0] is not space:
            finite = bool(np.isfinite(space.low).all() and np.isfinite(space.high).all())
            lows, highs = space.low - 1e-6, space.high + 1e-6
            bounds = self._action_bounds = (space, lows.ravel().tolist(), highs.ravel().tolist(), finite)
        _, low, high, finite = bounds
        # on Python floats (float32 converts exactly, so each comparison is numpy's): a worker wakes cold for each
        # action, and four numpy calls cost more than the loop. NaN fails these, and inf when the bounds are finite
        inside = all(lo <= x <= hi for lo, x, hi in zip(low, a.ravel().tolist(), high, strict=True))
        if not (inside and (finite or np.isfinite(a).all())):
            if not np.isfinite(a).all():
                raise gym_error.InvalidAction(f"action contains NaN or inf: {a.tolist()}")
            raise gym_error.InvalidAction(
                f"action {np.round(a, 4).tolist()} is outside the action space [{space.low.min()}, {space.high.max()}]"
            )
        return a

    # ---- for subclasses

    @abc.abstractmethod
    async def _astep(self, action: np.ndarray) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """Run in the loop thread: the body of ``step``."""

    @abc.abstractmethod
    async def _areset(self, options: dict[str, Any]) -> tuple[Any, dict[str, Any]]:
        """Run in the loop thread: the body of ``reset``."""

    @abc.abstractmethod
    async def _ahold(self) -> None:
        """Run in the loop thread: make the arm hold where it is."""


class GoalEnv(BaseEnv):
    """A BaseEnv with a dict observation (``observation``, ``achieved_goal``, ``desired_goal``) and the goal
    functions HER needs, vectorised over batches (leading dimensions of the goal arrays)."""

    @abc.abstractmethod
    def compute_reward(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any) -> np.ndarray:
        """Reward for each (achieved, desired) pair; ``info`` is a dict or an array of dicts."""

    @abc.abstractmethod
    def compute_terminated(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any) -> np.ndarray:
        """Whether each pair ends the episode."""

    def compute_truncated(self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any) -> np.ndarray:
        """Truncation is the TimeLimit wrapper's job: False for every pair."""
        return np.zeros(np.shape(achieved_goal)[:-1], dtype=bool)
