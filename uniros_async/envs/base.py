"""BaseEnv and GoalEnv: the gymnasium surface (step, reset, close, seeding) over an env loop in the background.

BaseEnv owns the protocol: it validates actions in the caller's thread (a bad action never reaches the arm: the
arm is told to hold, a gymnasium-style error is raised, and the env stays usable), refuses ``step`` before
``reset`` and after ``close``, and hands ``_astep`` / ``_areset`` to the loop thread under timeouts. What the
loop does is RobotEnv's business; what the numbers mean is TaskEnv's.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import error as gym_error

from uniros_async.envs.config import EnvConfig
from uniros_async.envs.runtime import LoopThread

__all__ = ["BaseEnv", "GoalEnv"]


class BaseEnv(gym.Env[Any, np.ndarray], abc.ABC):
    """A gymnasium.Env whose world runs on its own (see the module docstring)."""

    metadata: dict[str, Any] = {"render_modes": ["rgb_array"]}

    def __init__(self, config: EnvConfig) -> None:
        super().__init__()
        self.config = config
        self._rt: LoopThread | None = None
        self._closed = False
        self._needs_reset = True

    # ---- lifecycle

    def _start_runtime(self, main: Callable[..., Any], name: str, timeout_s: float) -> None:
        self._rt = LoopThread(main, name=name)
        self._rt.start(timeout_s)

    def _call(self, coro: Any, timeout_s: float) -> Any:
        assert self._rt is not None
        failure = self._rt_failure()
        if failure is not None:
            coro.close()
            raise failure
        try:
            return self._rt.call(coro, timeout_s)
        except RuntimeError:
            failure = self._rt_failure()
            if failure is not None:
                raise failure from None
            raise

    def _rt_failure(self) -> BaseException | None:
        rt = self._rt
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

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        """Stop the arm, move it home, sample a goal, wait until settled; return the first observation."""
        super().reset(seed=seed)
        self._check_open()
        obs, info = self._call(self._areset(options or {}), self.config.reset_timeout_s + self.config.step_timeout_s)
        self._needs_reset = False
        return obs, info

    def close(self) -> None:
        """Stop the env loop and everything it started (sim, processes, connections); idempotent."""
        if self._closed:
            return
        self._closed = True
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
        if not np.all(np.isfinite(a)):
            raise gym_error.InvalidAction(f"action contains NaN or inf: {a.tolist()}")
        if np.any(a < space.low - 1e-6) or np.any(a > space.high + 1e-6):
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
