"""Evaluate a policy: success rate, mean return and mean episode length over N episodes (deterministic actions).

``evaluate_policy`` runs a loaded model on a gymnasium env, ``evaluate_vec_policy`` on every env of a vector env
at once (concurrent training's evaluation); ``evaluate_checkpoint`` does what ``uniros eval``
does: load a checkpoint, make the env (padded and tagged as the checkpoint's training envs were), check that its
observation and action sizes fit the policy (a clear error naming both sizes if not), and evaluate.

A policy trained with ``normalize_obs`` sees every evaluation observation normalised with the run's statistics,
frozen: ``evaluate_policy`` takes them from the model's VecNormalize (the training env's current statistics during
training), ``load_policy`` attaches the checkpoint's; a checkpoint whose statistics are missing is an error.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from uniros_async.errors import ConfigError, EvaluationStopped
from uniros_async.training.checkpoint import (
    MODEL_FILE,
    CheckpointError,
    CheckpointMeta,
    check_obs_stats,
    check_sizes,
    find_checkpoint,
    load_obs_stats,
    read_meta,
)
from uniros_async.training.multitask import TaskIdObservation, build_env, space_sizes
from uniros_async.training.weights import is_weights_dir
from uniros_async.training.weights import load_policy as load_weights

__all__ = [
    "EvalResult",
    "EvaluationStopped",
    "evaluate_checkpoint",
    "evaluate_policy",
    "evaluate_vec_policy",
    "frozen_obs_stats",
    "load_policy",
    "make_eval_env",
]

logger = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvalResult:
    """The outcome of ``episodes`` evaluation episodes on one env."""

    label: str
    env_id: str
    episodes: int
    successes: int
    mean_return: float
    std_return: float
    mean_length: float
    seed: int | None
    env_kwargs: dict[str, Any] = dataclasses.field(default_factory=dict)
    normalized_obs: bool = False
    """Whether the policy saw the observations normalised with its checkpoint's statistics (``normalize_obs``)."""

    @property
    def success_rate(self) -> float:
        """Fraction of episodes that ended in success."""
        return self.successes / self.episodes if self.episodes else math.nan

    def summary(self) -> str:
        """One line: success rate, mean return, mean episode length."""
        return (
            f"{self.label}: success rate {100 * self.success_rate:.1f} % ({self.successes}/{self.episodes}), "
            f"mean return {self.mean_return:.2f} (std {self.std_return:.2f}), "
            f"mean episode length {self.mean_length:.1f}"
        )

    def to_dict(self) -> dict[str, Any]:
        """Plain data, with ``success_rate``."""
        return {**dataclasses.asdict(self), "success_rate": self.success_rate}


def evaluate_policy(
    model: Any,
    env: gym.Env[Any, Any],
    episodes: int,
    *,
    seed: int | None = 0,
    deterministic: bool = True,
    label: str = "",
    env_id: str = "",
    on_episode: Callable[[int, bool, float, int], None] | None = None,
) -> EvalResult:
    """Run ``episodes`` episodes with ``model.predict``; success is the last step's ``info["is_success"]``.

    The first reset gets ``seed`` (the env's goal sequence is then fixed), later ones continue its generator.
    ``on_episode(index, success, return, length)`` is called after each episode (progress bars).
    If the model has a VecNormalize (``model.get_vec_normalize_env()``: training with ``normalize_obs``, or
    attached by ``load_policy``), the policy sees the env's observations normalised with a frozen copy of its
    statistics taken at the start.
    """
    if episodes < 1:
        raise ConfigError(f"episodes must be >= 1, got {episodes}")
    get_stats = getattr(model, "get_vec_normalize_env", None)
    live = get_stats() if get_stats is not None else None
    stats = frozen_obs_stats(live) if live is not None else None
    returns: list[float] = []
    lengths: list[int] = []
    successes = 0
    for ep in range(episodes):
        obs, info = env.reset(seed=seed if ep == 0 else None)
        done, ret, length = False, 0.0, 0
        while not done:
            action, _ = model.predict(obs if stats is None else stats.normalize_obs(obs), deterministic=deterministic)
            obs, reward, terminated, truncated, info = env.step(action)
            ret += float(reward)
            length += 1
            done = bool(terminated or truncated)
        ok = bool(info.get("is_success", False))
        successes += ok
        returns.append(ret)
        lengths.append(length)
        if on_episode is not None:
            on_episode(ep, ok, ret, length)
    return EvalResult(
        label=label or env_id,
        env_id=env_id,
        episodes=episodes,
        successes=successes,
        mean_return=float(np.mean(returns)),
        std_return=float(np.std(returns)),
        mean_length=float(np.mean(lengths)),
        seed=seed,
        normalized_obs=stats is not None,
    )


def evaluate_vec_policy(
    model: Any,
    venv: Any,
    episodes: int,
    labels: Sequence[str],
    *,
    seed: int | None = 0,
    deterministic: bool = True,
    env_ids: Sequence[str] | None = None,
    stop: threading.Event | None = None,
) -> list[EvalResult]:
    """Evaluate on every env of an SB3 VecEnv at once: each step acts in all of them, until each has ended
    ``episodes`` episodes (an env that is done keeps acting, its further episodes not counted), so the envs are
    evaluated side by side instead of one after another (real-time envs: the wall time of the slowest env).

    The envs are reset first (with ``seed``, ``seed + 1``, ... when given) and left in mid-episode: reset them
    before training goes on. Observations are normalised as in ``evaluate_policy``. Success is the last step's
    ``info["is_success"]``.

    ``stop`` (an evaluation on a thread of its own): checked before every step; once set, the evaluation ends
    with ``EvaluationStopped``.

    Returns:
        One EvalResult per env, in order, labelled with ``labels``.
    """
    if episodes < 1:
        raise ConfigError(f"episodes must be >= 1, got {episodes}")
    n = int(venv.num_envs)
    if len(labels) != n:
        raise ConfigError(f"evaluate_vec_policy: {len(labels)} labels for {n} envs")
    get_stats = getattr(model, "get_vec_normalize_env", None)
    live = get_stats() if get_stats is not None else None
    stats = frozen_obs_stats(live) if live is not None else None
    if seed is not None:
        venv.seed(seed)
    obs = venv.reset()
    returns: list[list[float]] = [[] for _ in range(n)]
    lengths: list[list[int]] = [[] for _ in range(n)]
    wins = [0] * n
    ret, length = np.zeros(n), np.zeros(n, dtype=np.int64)
    while min(len(r) for r in returns) < episodes:
        if stop is not None and stop.is_set():
            raise EvaluationStopped(f"stopped with {min(len(r) for r in returns)} of {episodes} episodes per env")
        action, _ = model.predict(obs if stats is None else stats.normalize_obs(obs), deterministic=deterministic)
        obs, rewards, dones, infos = venv.step(action)
        ret += rewards
        length += 1
        for i in np.flatnonzero(dones):
            if len(returns[i]) < episodes:
                returns[i].append(float(ret[i]))
                lengths[i].append(int(length[i]))
                wins[i] += bool(infos[i].get("is_success", False))
            ret[i], length[i] = 0.0, 0
    ids = list(env_ids) if env_ids is not None else list(labels)
    return [
        EvalResult(
            label=labels[i],
            env_id=ids[i],
            episodes=episodes,
            successes=wins[i],
            mean_return=float(np.mean(returns[i])),
            std_return=float(np.std(returns[i])),
            mean_length=float(np.mean(lengths[i])),
            seed=seed,
            normalized_obs=stats is not None,
        )
        for i in range(n)
    ]


def frozen_obs_stats(vec_normalize: Any) -> Any:
    """A copy of a VecNormalize's observation statistics and settings, without its env, that no longer updates
    (``training=False``, ``norm_reward=False``): for ``normalize_obs`` only. (The pickle round trip of SB3's own
    ``VecNormalize.save``/``load``, which leaves the env out; statistics already without an env, as
    ``load_policy`` attaches them, are returned as they are: nothing steps them.)"""
    import pickle

    if vec_normalize.venv is None:  # unpickled and never given an env (SB3 cannot pickle those again)
        frozen = vec_normalize
    else:
        frozen = pickle.loads(pickle.dumps(vec_normalize, protocol=pickle.HIGHEST_PROTOCOL))
    frozen.training = False
    frozen.norm_reward = False
    return frozen


def _algo_class(name: str) -> type:
    if name == "AsyncTD3":
        from uniros_async.training.async_td3 import AsyncTD3  # lazy: it imports torch and SB3

        return AsyncTD3
    if name == "TD3":
        from stable_baselines3 import TD3

        return TD3
    raise CheckpointError(f"unknown algorithm {name!r} in the checkpoint's meta.json (expected TD3 or AsyncTD3)")


def training_kwargs(meta: CheckpointMeta, env_id: str, label: str | None = None) -> dict[str, Any] | None:
    """The kwargs the policy was trained with on ``env_id`` (``env_defaults`` filled in, ``clock`` left out: an
    evaluation picks its own), from the training env with that id (and ``label``, when given). None when the run
    did not train on that id, when several of its envs match (a multi-task run: give the label), or when the
    checkpoint's config cannot be read."""
    from uniros_async.training.config import train_config_from_dict

    try:
        cfg = train_config_from_dict(meta.config)
    except (ConfigError, TypeError, KeyError):
        return None
    found = [kw for lab, i, kw in cfg.env_specs() if i == env_id and (label is None or lab == label)]
    if len(found) != 1:
        return None
    return {k: v for k, v in found[0].items() if k != "clock"}


def load_policy(checkpoint: str | Path) -> tuple[Any, CheckpointMeta, Path]:
    """Load a checkpoint's model for prediction only (a one-row replay buffer, no env attached), or a weights
    directory's policy (weights.py).

    A checkpoint trained with ``normalize_obs`` gets its observation statistics attached, frozen (the model's
    ``get_vec_normalize_env()``): ``evaluate_policy`` normalises with them; call ``model.predict`` yourself with
    ``model.get_vec_normalize_env().normalize_obs(obs)``.

    Returns:
        (model, meta, checkpoint directory).

    Raises:
        CheckpointError: no checkpoint at ``checkpoint``, an unreadable one, or one trained on normalised
            observations whose statistics are missing.
    """
    from stable_baselines3.common.buffers import DictReplayBuffer, ReplayBuffer

    ckpt = find_checkpoint(checkpoint)
    meta = read_meta(ckpt)
    if is_weights_dir(ckpt):
        return load_weights(ckpt), meta, ckpt  # normalises its observations itself
    cls = _algo_class(meta.algo)
    # predict needs no replay buffer: a one-row plain one avoids allocating 1e6 rows (and HER's need of an env)
    custom: dict[str, Any] = {
        "buffer_size": 1,
        "replay_buffer_class": DictReplayBuffer if meta.goal_env else ReplayBuffer,
        "replay_buffer_kwargs": {},
        "learning_starts": 0,
    }
    try:
        model = cls.load(ckpt / MODEL_FILE, device="cpu", custom_objects=custom)  # type: ignore[attr-defined]
    except (OSError, ValueError, KeyError, RuntimeError) as exc:
        raise CheckpointError(f"cannot load {ckpt / MODEL_FILE}: {exc}") from exc
    stats = load_obs_stats(ckpt)
    if stats is not None:
        model._vec_normalize_env = stats  # SB3's own slot (what get_vec_normalize_env returns); never saved
    return model, meta, ckpt


def make_eval_env(
    meta: CheckpointMeta,
    env_id: str,
    kwargs: dict[str, Any],
    *,
    label: str | None = None,
    placement: str = "inprocess",
) -> gym.Env[Any, Any]:
    """Make ``env_id`` as the checkpoint's policy expects it: padded to its sizes, with its task index if any.

    Raises:
        CheckpointError: the env's observation or action size (after padding) differs from the policy's (both
            named), or a task-indexed policy gets an env it was not trained on.
        ConfigError: an unknown id or keyword argument.
    """
    delay = meta.config.get("delay_aware")  # the run's TrainConfig.delay_aware, as plain data
    env = build_env(
        env_id,
        kwargs,
        placement=placement,
        drop_observation=meta.drop_observation,
        delay_aware=None if not delay else (int(delay["action_history"]), bool(delay["observation_age"])),
    )
    try:
        goal = isinstance(env.observation_space, gym.spaces.Dict)
        obs_size, act_size = space_sizes(env)
        where = f"{env_id} {kwargs}" if kwargs else env_id
        if meta.pad_to is not None and obs_size <= meta.pad_to[0] and act_size <= meta.pad_to[1]:
            from uniros_async.envs.wrappers import PadSpaces

            if (obs_size, act_size) != tuple(meta.pad_to):
                env = PadSpaces(env, *meta.pad_to)
            obs_size, act_size = meta.pad_to
        if meta.task_id_size:
            if label is None or label not in meta.labels:
                raise CheckpointError(
                    f"the checkpoint's policy takes a task index; give the env one of its training labels "
                    f"{list(meta.labels)} (got {label!r})"
                )
            env = TaskIdObservation(env, meta.labels.index(label), meta.task_id_size)
            obs_size += meta.task_id_size
        check_sizes(meta, obs_size, act_size, goal, where)
    except BaseException:
        env.close()
        raise
    return env


def evaluate_checkpoint(
    checkpoint: str | Path,
    env_id: str,
    kwargs: dict[str, Any] | None = None,
    *,
    episodes: int = 200,
    seed: int | None = 0,
    label: str | None = None,
    placement: str = "inprocess",
    on_episode: Callable[[int, bool, float, int], None] | None = None,
    record: str | Path | None = None,
    record_episodes_per_file: int | None = None,
) -> EvalResult:
    """Load a checkpoint and evaluate it on ``env_id`` (see the module docstring and ``make_eval_env``); with
    ``record``, every step goes to that MCAP bag (``bag.episodes.RecordEpisodes``; a new file every
    ``record_episodes_per_file`` episodes)."""
    kwargs = dict(kwargs or {})
    model, meta, _ = load_policy(checkpoint)
    env = make_eval_env(meta, env_id, kwargs, label=label, placement=placement)
    if record is not None:
        from uniros_async.bag.episodes import RecordEpisodes

        env = RecordEpisodes(env, record, episodes_per_file=record_episodes_per_file)
    try:
        stats = model.get_vec_normalize_env()
        if stats is not None:
            check_obs_stats(stats, env.observation_space, f"{env_id} {kwargs}" if kwargs else env_id)
        result = evaluate_policy(
            model, env, episodes, seed=seed, label=label or env_id, env_id=env_id, on_episode=on_episode
        )
    finally:
        env.close()
    # a weights policy normalises inside itself: meta.json says whether it does
    return dataclasses.replace(result, env_kwargs=kwargs, normalized_obs=result.normalized_obs or meta.normalize_obs)
