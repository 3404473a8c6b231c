"""Concurrent multi-task training (``concurrent: true``): every env acts in every action cycle.

``TaskSamplerEnv`` (multitask.py) steps one env per episode, the paper's Algorithm 1: right for accelerated sim,
where an env costs only the compute it takes, but in real time it leaves every other arm standing idle. Here the
training envs run as one vector env over worker processes (``uniros_async.make_vec``, padded to common sizes):
each step sends an action to every env at once and returns when all of them have ended their action cycle, so
four arms give four transitions per 0.8 s cycle, all into the one replay buffer of the one policy.

``ConcurrentVecEnv`` is the SB3 VecEnv wrapper the learner steps. It tags every info with its env's label
(``info["task"]``, ``info["task_index"]``), with ``task_id`` appends a one-hot env index to every observation (the
``observation`` key of a goal env; ``terminal_observation`` too), so that one policy can tell arms apart whose padded
observations and actions mean different joints, records when the agent received each step's returns and which steps
ended an episode, and on ``timing_window()`` reads every env's timing records from its worker (cleared after the
read) and turns them into the action-cycle statistics of ``uniros bench latency`` (``stats.loop_metrics``): the
period between the agent's actions reaching each env loop, periods spanning a reset left out. The evaluation
(``evaluate.evaluate_vec_policy``) steps the same envs, all four at once, between two training windows; with
``eval.alongside`` a second ConcurrentVecEnv of the same envs is evaluated in a process of its own while training
goes on (alongside.py).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper

from uniros_async.errors import ConfigError
from uniros_async.training.multitask import task_id_space, with_task_id

__all__ = ["ConcurrentVecEnv", "TaskIdVecEnv", "open_concurrent_env"]

TIMING_METRICS = ("action_cycle", "actuator_cycle", "observation_age")


def open_concurrent_env(
    specs: Sequence[tuple[str, str, dict[str, Any]]],
    *,
    start_timeout_s: float = 120.0,
    rt_rank_base: int = 0,
    loop_phase_base: int | None = None,
    task_id: bool = False,
) -> ConcurrentVecEnv:
    """The envs ``specs`` (label, id, kwargs) as one ``ConcurrentVecEnv`` over worker processes (padded; their
    loops' real-time ranks from ``rt_rank_base`` up and their tick phases from ``loop_phase_base`` up, ``make_vec``;
    a one-hot env index in every observation with ``task_id``).

    Raises:
        ConfigError: an unknown id or keyword argument, or spaces that cannot be padded together.
        WorkerError: a worker failed to start.
    """
    from uniros_async.runtime import make_vec

    vec = make_vec(
        [(env_id, dict(kw)) for _, env_id, kw in specs],
        pad=True,
        start_timeout_s=start_timeout_s,
        rt_rank_base=rt_rank_base,
        loop_phase_base=loop_phase_base,
    )
    try:
        return ConcurrentVecEnv(vec.as_sb3(), [label for label, _, _ in specs], task_id=task_id)
    except BaseException:
        vec.close()
        raise


class ConcurrentVecEnv(VecEnvWrapper):
    """Labels, receive times and action-cycle statistics of a vector env's steps; see the module docstring.

    Args:
        venv: the SB3 VecEnv over the workers (``make_vec(...).as_sb3()``).
        labels: one label per sub-env, in order.
        task_id: append the sub-env's one-hot index to its observations (the ``observation`` key of a goal env).
    """

    def __init__(self, venv: VecEnv, labels: Sequence[str], *, task_id: bool = False) -> None:
        if len(labels) != venv.num_envs:
            raise ConfigError(f"ConcurrentVecEnv: {len(labels)} labels for {venv.num_envs} envs")
        super().__init__(TaskIdVecEnv(venv) if task_id else venv)
        self.labels = list(labels)
        self._recv_ns: list[int] = []
        self._reset_after: set[int] = set()
        self.samples: dict[str, dict[str, list[float]]] = {lab: {m: [] for m in TIMING_METRICS} for lab in labels}
        """Every window's samples so far, per env label and metric (ms)."""
        self.step_overruns = dict.fromkeys(self.labels, 0)

    def reset(self) -> Any:
        """Reset every env and start a new timing window (what the reset itself recorded is dropped)."""
        obs = self.venv.reset()
        self.restart_window()
        return obs

    def step_wait(self) -> Any:
        """The vector step's returns, infos tagged with the env's label."""
        obs, rewards, dones, infos = self.venv.step_wait()
        self._recv_ns.append(time.monotonic_ns())
        if bool(np.any(dones)):
            self._reset_after.add(len(self._recv_ns) - 1)
        for i, info in enumerate(infos):
            info["task"] = self.labels[i]
            info["task_index"] = i
        return obs, rewards, dones, infos

    def restart_window(self) -> None:
        """Drop the timing recorded so far (e.g. an evaluation's, or a reset's) and start a new window."""
        self.venv.env_method("timing_snapshot", clear=True)
        self._recv_ns.clear()
        self._reset_after.clear()

    def timing_window(self) -> dict[str, dict[str, list[float]]]:
        """The timing samples (ms) of every env since the window started, per label and metric; starts the next.

        Call it between steps (after a step's returns, before the next actions): the next window then starts with
        the next step, whose period from this one is in neither window.
        """
        from uniros_async.stats import loop_metrics

        snaps = self.venv.env_method("timing_snapshot", clear=True)
        out: dict[str, dict[str, list[float]]] = {}
        for label, snap in zip(self.labels, snaps, strict=True):
            m = loop_metrics(snap, reset_after=self._reset_after, recv_ns=self._recv_ns)
            out[label] = {k: m[k] for k in TIMING_METRICS}
            for k in TIMING_METRICS:
                self.samples[label][k].extend(m[k])
            self.step_overruns[label] += int(snap.get("step_overruns", 0))
        self._recv_ns.clear()
        self._reset_after.clear()
        return out


class TaskIdVecEnv(VecEnvWrapper):
    """A vector env whose every observation ends with its sub-env's one-hot index (the ``observation`` key of a goal
    env), the observation an episode ended on (``info["terminal_observation"]``) included; ``TaskIdObservation``
    for a vector env.

    Raises:
        ConfigError: an observation with no 1-D Box to append to.
    """

    def __init__(self, venv: VecEnv) -> None:
        self._ids = np.eye(venv.num_envs, dtype=np.float32)
        super().__init__(venv, observation_space=task_id_space(venv.observation_space, venv.num_envs))

    def reset(self) -> Any:
        return with_task_id(self.venv.reset(), self._ids)

    def step_wait(self) -> Any:
        obs, rewards, dones, infos = self.venv.step_wait()
        for i, info in enumerate(infos):
            if "terminal_observation" in info:
                info["terminal_observation"] = with_task_id(info["terminal_observation"], self._ids[i])
        return with_task_id(obs, self._ids), rewards, dones, infos
