"""The SB3 ``VecEnv`` over a ``UnirosVectorEnv``'s workers: ``UnirosVectorEnv.as_sb3()`` returns one.

SB3's conventions, as its DummyVecEnv has them: the step that ends an episode resets that sub-env at once (the
workers' same-step autoreset), its info holds ``terminal_observation`` and ``TimeLimit.truncated``, and the reset's
info goes to ``reset_infos``. ``get_attr``, ``set_attr``, ``env_method`` and ``env_is_wrapped`` are answered by the
workers, where the envs and their wrappers live.

Imported on first use (``as_sb3``): SB3 imports torch, which a plain gymnasium user need not pay for. The vector env
is taken as it comes (its type is not imported here: vector.py imports this module).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv as SB3VecEnv

from uniros_async.errors import WorkerError
from uniros_async.runtime.protocol import conform, result_value

__all__ = ["UnirosSB3VecEnv"]


class UnirosSB3VecEnv(SB3VecEnv):
    """An SB3 VecEnv over the workers of a UnirosVectorEnv, with SB3's conventions (as DummyVecEnv): the step
    that ends an episode resets at once; its info holds ``terminal_observation`` and ``TimeLimit.truncated``;
    the reset's info goes to ``reset_infos``."""

    def __init__(self, venv: Any) -> None:
        self.venv = venv
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)

    def reset(self) -> Any:
        v = self.venv
        v._check_open()
        v._drop_pending()
        msgs = [
            {"op": "reset", "seed": self._seeds[i], "options": self._options[i] or None} for i in range(self.num_envs)
        ]
        replies = v._sup.call(v._sup.request_all(msgs))
        self.reset_infos = [r[1] for r in replies]
        self._reset_seeds()
        self._reset_options()
        return v._stack_obs([r[0] for r in replies])

    def step_async(self, actions: np.ndarray) -> None:
        v = self.venv
        v._check_open()
        if v._pending is not None:
            raise gym.error.AlreadyPendingCallError("step_async was called twice without step_wait", "step")
        msgs = v._step_messages(actions, "same_step")
        v._pending = v._sup.submit_steps(msgs)

    def step_wait(self) -> tuple[Any, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        v = self.venv
        replies = v._wait(None)
        infos: list[dict[str, Any]] = []
        dones = np.zeros(self.num_envs, dtype=np.bool_)
        space = v.single_observation_space
        for i, (_, _, terminated, truncated, info) in enumerate(replies):
            done = dones[i] = terminated or truncated
            if "final_obs" in info:  # the worker reset after the step (protocol: same_step)
                reset_info = {k: x for k, x in info.items() if k not in ("final_obs", "final_info")}
                self.reset_infos[i] = reset_info
                final = info["final_obs"]
                info = dict(info["final_info"])
                info["terminal_observation"] = conform(space, final) if v._conform_obs else final
            elif done:  # a restarted worker: its final observation died with it
                info["terminal_observation"] = replies[i][0]
            info["TimeLimit.truncated"] = bool(truncated and not terminated)
            infos.append(info)
        obs = v._stack_obs([r[0] for r in replies])
        rewards = np.array([r[1] for r in replies], dtype=np.float32)
        return obs, rewards, dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_images(self) -> Sequence[np.ndarray | None]:
        if self.render_mode != "rgb_array":
            import warnings

            warnings.warn(
                f"The render mode is {self.render_mode}, but this method assumes it is `rgb_array` to obtain images.",
                stacklevel=2,
            )
            return [None] * self.num_envs
        return list(self.venv.render() or ())

    def _targets(self, indices: Any) -> list[int]:
        """``indices`` as SB3 takes them (None: all; an int; an iterable; negative ones count from the end).

        Raises:
            IndexError: an index out of range.
        """
        n = self.num_envs
        if indices is None:
            return list(range(n))
        if isinstance(indices, int | np.integer):
            indices = [indices]
        out = []
        for i in indices:
            k = int(i)
            if not -n <= k < n:
                raise IndexError(f"env index {k} out of range for {n} envs")
            out.append(k % n)
        return out

    def _each(self, msg: dict[str, Any], indices: Any) -> list[Any]:
        """``msg`` to each worker of ``indices``, in their order (an index named twice gets it twice); the
        results in that order."""
        v = self.venv
        v._check_open()
        targets = self._targets(indices)
        results: list[Any] = [None] * len(targets)
        todo = list(enumerate(targets))
        while todo:  # one request per worker at a time: a repeated index waits for the next round
            round_: list[tuple[int, int]] = []
            later: list[tuple[int, int]] = []
            seen: set[int] = set()
            for pos, i in todo:
                (later if i in seen else round_).append((pos, i))
                seen.add(i)
            msgs: list[Any] = [None] * self.num_envs
            for _, i in round_:
                msgs[i] = msg
            try:
                out = v._sup.call(v._sup.request_all(msgs))
            except WorkerError as exc:
                if "AttributeError" in str(exc):
                    raise AttributeError(str(exc)) from exc
                raise
            for pos, i in round_:
                results[pos] = result_value(out[i])
            todo = later
        return results

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        return self._each({"op": "get", "name": attr_name}, indices)

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        self._each({"op": "set", "name": attr_name, "value": value}, indices)

    def env_method(self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any) -> list[Any]:
        msg = {"op": "call", "name": method_name, "args": list(method_args), "kwargs": method_kwargs}
        return self._each(msg, indices)

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        """Asked of each worker's env (its wrappers live there)."""
        name = f"{wrapper_class.__module__}:{wrapper_class.__qualname__}"
        return [bool(r) for r in self._each({"op": "is_wrapped", "wrapper": name}, indices)]
