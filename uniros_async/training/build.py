"""Building a training run's envs and model from its ``TrainConfig``: the training envs (one ``TaskSamplerEnv``, or
one ``ConcurrentVecEnv`` over worker processes), the evaluation envs shaped as the training envs, SB3's VecEnv
around them (with ``VecNormalize`` under ``normalize_obs``), and the TD3 or TD3 + HER model with its settings.
"""

from __future__ import annotations

import contextlib
import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np

from uniros_async.envs.config import EnvConfig
from uniros_async.errors import ConfigError
from uniros_async.training.checkpoint import load_obs_stats
from uniros_async.training.config import TrainConfig
from uniros_async.training.multitask import TaskIdObservation, TaskSamplerEnv, build_env, space_sizes

if TYPE_CHECKING:
    from uniros_async.training.concurrent import ConcurrentVecEnv

__all__ = [
    "GOAL_KEYS",
    "OBS_CLIP",
    "EnvLayout",
    "algo_class",
    "build_concurrent_env",
    "build_eval_envs",
    "build_model",
    "build_train_env",
    "close_all",
    "model_kwargs",
    "real_time_actor",
    "use_her",
    "vec_env",
]


@dataclasses.dataclass(frozen=True, kw_only=True)
class EnvLayout:
    """How the training envs were shaped: padding, task index, kind."""

    pad_to: tuple[int, int] | None
    task_id_size: int
    goal_env: bool
    obs_size: int
    action_size: int
    labels: tuple[str, ...]
    n_envs: int = 1


def close_all(envs: list[gym.Env[Any, Any]]) -> None:
    for e in envs:
        with contextlib.suppress(Exception):
            e.close()


def build_train_env(cfg: TrainConfig) -> tuple[TaskSamplerEnv, EnvLayout]:
    """The training envs as one TaskSamplerEnv (padded, task-indexed if asked) and their layout.

    Raises:
        ConfigError: unknown ids or arguments, mixed goal and standard envs, or HER asked on standard envs.
        WorkerError: a worker failed to start (``placement: workers``).
    """
    specs = cfg.env_specs()
    envs: list[gym.Env[Any, Any]] = []
    try:
        for _, env_id, kwargs in specs:
            envs.append(
                build_env(
                    env_id,
                    kwargs,
                    placement=cfg.placement,
                    drop_observation=cfg.drop_observation,
                    delay_aware=cfg.delay_aware_args(),
                )
            )
        sizes = [space_sizes(e) for e in envs]
        kinds = {isinstance(e.observation_space, gym.spaces.Dict) for e in envs}
        if len(kinds) != 1:
            raise ConfigError(f"envs mix goal (dict observation) and standard envs: {cfg.labels()}")
        goal = kinds.pop()
        pad_to: tuple[int, int] | None = None
        if len(set(sizes)) > 1:
            pad_to = (max(s[0] for s in sizes), max(s[1] for s in sizes))
            from uniros_async.envs.wrappers import PadSpaces

            envs = [PadSpaces(e, *pad_to) if s != pad_to else e for e, s in zip(envs, sizes, strict=True)]
        n_id = len(envs) if cfg.task_id_in_obs else 0
        if n_id:
            envs = [TaskIdObservation(e, i, n_id) for i, e in enumerate(envs)]
        sampler = TaskSamplerEnv(envs, cfg.labels(), seed=cfg.seed)
    except BaseException:
        close_all(envs)
        raise
    obs_size, act_size = space_sizes(sampler)
    layout = EnvLayout(
        pad_to=pad_to,
        task_id_size=n_id,
        goal_env=goal,
        obs_size=obs_size,
        action_size=act_size,
        labels=tuple(cfg.labels()),
    )
    return sampler, layout


def build_concurrent_env(
    cfg: TrainConfig, *, rt_rank_base: int = 0, loop_phase_base: int | None = None
) -> tuple[ConcurrentVecEnv, EnvLayout]:
    """The training envs as one ConcurrentVecEnv over worker processes (``concurrent: true``) and their layout; their
    loops' real-time ranks from ``rt_rank_base`` up and tick phases from ``loop_phase_base`` up (``make_vec``).

    Raises:
        ConfigError: unknown ids or arguments, or mixed goal and standard envs.
        WorkerError: a worker failed to start.
    """
    from uniros_async.training.concurrent import open_concurrent_env

    venv = open_concurrent_env(
        cfg.env_specs(), rt_rank_base=rt_rank_base, loop_phase_base=loop_phase_base, task_id=cfg.task_id_in_obs
    )
    try:
        goal = isinstance(venv.observation_space, gym.spaces.Dict)
        box = venv.observation_space["observation"] if goal else venv.observation_space  # type: ignore[index]
        obs_size, act_size = int(box.shape[0]), int(venv.action_space.shape[0])  # type: ignore[index]
        n_id = venv.num_envs if cfg.task_id_in_obs else 0
    except BaseException:
        venv.close()
        raise
    layout = EnvLayout(
        pad_to=(obs_size - n_id, act_size) if len(cfg.envs) > 1 else None,
        task_id_size=n_id,
        goal_env=goal,
        obs_size=obs_size,
        action_size=act_size,
        labels=tuple(cfg.labels()),
        n_envs=venv.num_envs,
    )
    return venv, layout


def build_eval_envs(cfg: TrainConfig, layout: EnvLayout) -> list[tuple[str, str, gym.Env[Any, Any]]]:
    """(label, id, env) for every evaluation env, shaped as the training envs."""
    from uniros_async.envs.wrappers import PadSpaces

    out: list[tuple[str, str, gym.Env[Any, Any]]] = []
    try:
        for label, env_id, kwargs in cfg.eval_specs():
            env = build_env(
                env_id,
                kwargs,
                placement=cfg.placement,
                drop_observation=cfg.drop_observation,
                delay_aware=cfg.delay_aware_args(),
            )
            out.append((label, env_id, env))
            if layout.pad_to is not None and space_sizes(env) != layout.pad_to:
                env = PadSpaces(env, *layout.pad_to)
            if layout.task_id_size:
                if label not in layout.labels:
                    raise ConfigError(
                        f"eval env {label!r}: with task_id_in_obs every eval env must be a training env "
                        f"{list(layout.labels)}"
                    )
                env = TaskIdObservation(env, layout.labels.index(label), layout.task_id_size)
            out[-1] = (label, env_id, env)
            o, a = space_sizes(env)
            if (o, a) != (layout.obs_size, layout.action_size):
                raise ConfigError(
                    f"eval env {label!r} has observation size {o} and action size {a}; the policy takes "
                    f"{layout.obs_size} and {layout.action_size}"
                )
    except BaseException:
        close_all([e for _, _, e in out])
        raise
    return out


def use_her(cfg: TrainConfig, layout: EnvLayout) -> bool:
    if cfg.replay_buffer == "her" and not layout.goal_env:
        raise ConfigError(f"replay_buffer: her needs goal envs (dict observations); {list(layout.labels)} are not")
    return cfg.replay_buffer == "her" or (cfg.replay_buffer == "auto" and layout.goal_env)


def algo_class(cfg: TrainConfig) -> type:
    if cfg.learner == "async":
        try:
            from uniros_async.training.async_td3 import AsyncTD3  # lazy: only the async learner needs it
        except ImportError as exc:
            raise ConfigError(f"learner: async needs uniros_async.training.async_td3 ({exc})") from exc
        return AsyncTD3
    from stable_baselines3 import TD3

    return TD3


def model_kwargs(cfg: TrainConfig, layout: EnvLayout, run_dir: Path) -> dict[str, Any]:
    """SB3 TD3 constructor arguments from the config (the policy and env excluded)."""
    from stable_baselines3.common.noise import NormalActionNoise, VectorizedActionNoise

    t = cfg.td3
    noise: Any = None
    if t.action_noise_std > 0:
        noise = NormalActionNoise(np.zeros(layout.action_size), np.full(layout.action_size, t.action_noise_std))
        if layout.n_envs > 1:  # a draw of its own for every env (one noise broadcast to all would be correlated)
            noise = VectorizedActionNoise(noise, layout.n_envs)
    kw: dict[str, Any] = {
        "learning_rate": t.learning_rate,
        "buffer_size": t.buffer_size,
        "learning_starts": t.learning_starts,
        "batch_size": t.batch_size,
        "tau": t.tau,
        "gamma": t.gamma,
        "train_freq": (t.train_freq, "step"),
        "gradient_steps": t.gradient_steps,
        "policy_delay": t.policy_delay,
        "target_policy_noise": t.target_policy_noise,
        "target_noise_clip": t.target_noise_clip,
        "policy_kwargs": {"net_arch": list(t.net_arch)},
        "action_noise": noise,
        "tensorboard_log": str(run_dir / "tb"),
        "seed": cfg.seed,
        "device": "cpu",
        "verbose": 0,
    }
    if use_her(cfg, layout):
        from stable_baselines3 import HerReplayBuffer

        kw["replay_buffer_class"] = HerReplayBuffer
        kw["replay_buffer_kwargs"] = {
            "n_sampled_goal": cfg.her.n_sampled_goal,
            "goal_selection_strategy": cfg.her.goal_selection_strategy,
        }
    if cfg.learner == "async":
        kw["updates_per_step"] = cfg.async_learner.updates_per_step
        kw["sync_every"] = cfg.async_learner.sync_every
        kw["real_time_actor"] = real_time_actor(cfg)
        kw["action_l2"] = cfg.async_learner.action_l2
        kw["torch_threads"] = cfg.torch_threads
    return kw


def real_time_actor(cfg: TrainConfig) -> bool:
    """Whether the threads that act on the envs (AsyncTD3's acting thread, the evaluation alongside) run in the
    real-time class: ``async_learner.real_time_actor`` if set, else whether any training env runs on the wall
    clock (accelerated envs compute flat out and must not starve other processes)."""
    rt_actor = cfg.async_learner.real_time_actor
    if rt_actor is None:
        rt_actor = any(EnvConfig.split({**cfg.env_defaults, **e.kwargs})[0].clock == "wall" for e in cfg.envs)
    return bool(rt_actor)


GOAL_KEYS = ("observation", "achieved_goal", "desired_goal")

OBS_CLIP = 10.0  # VecNormalize's default, rl-baselines3-zoo's with ``normalize: true``


def vec_env(cfg: TrainConfig, env: Any, layout: EnvLayout, resume_from: Path | None = None) -> Any:
    """The training VecEnv: Monitor, DummyVecEnv, local HER rewards for workers, and with ``normalize_obs`` a
    VecNormalize on top (fresh, or the statistics of the checkpoint ``resume_from``)."""
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor, VecNormalize

    if cfg.concurrent:
        vec: Any = VecMonitor(env, info_keywords=("is_success",))
    else:
        vec = DummyVecEnv([lambda: Monitor(env, info_keywords=("is_success",))])
    if cfg.placement in ("workers", "ray") and use_her(cfg, layout):
        # HER relabels batches of goals through env_method("compute_reward"): answer it here, not in the workers
        try:
            from uniros_async.training.her import LocalGoalReward
        except ImportError:
            pass  # TaskSamplerEnv.compute_reward asks the first worker instead (slower, same result)
        else:
            vec = LocalGoalReward(vec)
    if cfg.normalize_obs:
        if resume_from is not None:
            vec = load_obs_stats(resume_from, vec)  # training=True: the statistics go on from the checkpoint's
        else:
            space = vec.observation_space
            keys = [k for k in GOAL_KEYS if k in space.spaces] if isinstance(space, gym.spaces.Dict) else None
            vec = VecNormalize(
                vec,
                training=True,
                norm_obs=True,
                norm_reward=False,
                clip_obs=OBS_CLIP,
                gamma=cfg.td3.gamma,
                norm_obs_keys=keys,
            )
    return vec


def build_model(cfg: TrainConfig, vec_env: Any, layout: EnvLayout, run_dir: Path) -> Any:
    """A fresh TD3 / AsyncTD3 (with HER for goal envs) for the config."""
    cls = algo_class(cfg)
    policy = "MultiInputPolicy" if layout.goal_env else "MlpPolicy"
    return cls(policy, vec_env, **model_kwargs(cfg, layout, run_dir))
