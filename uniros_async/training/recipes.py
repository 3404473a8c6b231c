"""SB3 recipes: TD3 for standard envs, TD3 + HerReplayBuffer for goal envs, single- or multi-task, with periodic
evaluation, TensorBoard logs, CSV learning curves and atomic checkpoints; ``train(cfg)`` runs one TrainConfig.

A run directory holds::

    config.yaml      the resolved config (``uniros train --resume --run-dir DIR`` reads it back)
    episodes.csv     one row per training episode: step, task, return, length, success
    eval.csv         one row per evaluation and env: step, task, success_rate, mean_return, mean_length, episodes
    final_eval.json  the last evaluation, per env
    tb/              TensorBoard (SB3's scalars plus train/success_rate/<env> and eval/*/<env>)
    checkpoints/     see checkpoint.py

Every env goes through ``TaskSamplerEnv`` (multitask.py): with one env it only tags infos; with several it is the
paper's Algorithm 1 (an env sampled per episode, one replay buffer, one policy). Interruption (Ctrl-C, SIGTERM,
a dead worker) stops the run and leaves the last checkpoint intact; ``train(cfg, resume=True)`` continues from it
(model, optimisers, step counter, action noise and replay buffer; the env starts a fresh episode).

With ``normalize_obs`` the training VecEnv is wrapped in SB3's ``VecNormalize`` (observations only, statistics
updated as it steps): SB3 stores raw observations in the replay buffer and normalises them when it samples a batch
(HER relabels raw goals first), so relabelling and rewards never see normalised values. The statistics go into
every checkpoint (checkpoint.py), come back on resume, and every evaluation normalises with a frozen copy.
"""

from __future__ import annotations

import collections
import contextlib
import csv
import dataclasses
import io
import json
import logging
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import yaml

from uniros_async.envs.config import EnvConfig
from uniros_async.errors import ConfigError, UnirosError
from uniros_async.training.checkpoint import (
    CheckpointError,
    CheckpointMeta,
    check_sizes,
    clean_partial,
    latest_checkpoint,
    load_obs_stats,
    load_replay_buffer,
    read_meta,
    save_checkpoint,
    write_atomic,
)
from uniros_async.training.config import TrainConfig, config_to_dict
from uniros_async.training.evaluate import EvalResult, evaluate_policy
from uniros_async.training.multitask import TaskIdObservation, TaskSamplerEnv, build_env, space_sizes

__all__ = ["TrainResult", "TrainingInterrupted", "build_model", "build_train_env", "train"]

logger = logging.getLogger(__name__)

EPISODE_FIELDS = ("step", "task", "return", "length", "success")
EVAL_FIELDS = ("step", "task", "success_rate", "mean_return", "mean_length", "episodes")


class TrainingInterrupted(UnirosError):
    """The run was stopped (Ctrl-C, SIGTERM) before ``total_steps``; ``checkpoint`` is the newest intact one."""

    def __init__(self, message: str, checkpoint: Path | None) -> None:
        super().__init__(message)
        self.checkpoint = checkpoint


@dataclasses.dataclass(frozen=True, kw_only=True)
class TrainResult:
    """What ``train`` returns."""

    run_dir: Path
    steps: int
    checkpoint: Path
    final_eval: list[EvalResult]
    wall_time_s: float


@dataclasses.dataclass(frozen=True, kw_only=True)
class EnvLayout:
    """How the training envs were shaped: padding, task index, kind."""

    pad_to: tuple[int, int] | None
    task_id_size: int
    goal_env: bool
    obs_size: int
    action_size: int
    labels: tuple[str, ...]


# ---------------------------------------------------------------- envs


def _close_all(envs: list[gym.Env[Any, Any]]) -> None:
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
            envs.append(build_env(env_id, kwargs, placement=cfg.placement, drop_observation=cfg.drop_observation))
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
        _close_all(envs)
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


def build_eval_envs(cfg: TrainConfig, layout: EnvLayout) -> list[tuple[str, str, gym.Env[Any, Any]]]:
    """(label, id, env) for every evaluation env, shaped as the training envs."""
    from uniros_async.envs.wrappers import PadSpaces

    out: list[tuple[str, str, gym.Env[Any, Any]]] = []
    try:
        for label, env_id, kwargs in cfg.eval_specs():
            env = build_env(env_id, kwargs, placement=cfg.placement, drop_observation=cfg.drop_observation)
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
        _close_all([e for _, _, e in out])
        raise
    return out


# ---------------------------------------------------------------- model


def _use_her(cfg: TrainConfig, layout: EnvLayout) -> bool:
    if cfg.replay_buffer == "her" and not layout.goal_env:
        raise ConfigError(f"replay_buffer: her needs goal envs (dict observations); {list(layout.labels)} are not")
    return cfg.replay_buffer == "her" or (cfg.replay_buffer == "auto" and layout.goal_env)


def _algo_class(cfg: TrainConfig) -> type:
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
    from stable_baselines3.common.noise import NormalActionNoise

    t = cfg.td3
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
        "action_noise": (
            NormalActionNoise(np.zeros(layout.action_size), np.full(layout.action_size, t.action_noise_std))
            if t.action_noise_std > 0
            else None
        ),
        "tensorboard_log": str(run_dir / "tb"),
        "seed": cfg.seed,
        "device": "cpu",
        "verbose": 0,
    }
    if _use_her(cfg, layout):
        from stable_baselines3 import HerReplayBuffer

        kw["replay_buffer_class"] = HerReplayBuffer
        kw["replay_buffer_kwargs"] = {
            "n_sampled_goal": cfg.her.n_sampled_goal,
            "goal_selection_strategy": cfg.her.goal_selection_strategy,
        }
    if cfg.learner == "async":
        kw["updates_per_step"] = cfg.async_learner.updates_per_step
        kw["sync_every"] = cfg.async_learner.sync_every
        rt_actor = cfg.async_learner.real_time_actor
        if rt_actor is None:  # real-time envs get a real-time acting thread; accelerated ones compute flat out
            rt_actor = any(EnvConfig.split({**cfg.env_defaults, **e.kwargs})[0].clock == "wall" for e in cfg.envs)
        kw["real_time_actor"] = rt_actor
        kw["action_l2"] = cfg.async_learner.action_l2
        kw["torch_threads"] = cfg.torch_threads
    return kw


GOAL_KEYS = ("observation", "achieved_goal", "desired_goal")
OBS_CLIP = 10.0  # VecNormalize's default, rl-baselines3-zoo's with ``normalize: true``


def _vec_env(cfg: TrainConfig, env: gym.Env[Any, Any], layout: EnvLayout, resume_from: Path | None = None) -> Any:
    """The training VecEnv: Monitor, DummyVecEnv, local HER rewards for workers, and with ``normalize_obs`` a
    VecNormalize on top (fresh, or the statistics of the checkpoint ``resume_from``)."""
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    vec: Any = DummyVecEnv([lambda: Monitor(env, info_keywords=("is_success",))])
    if cfg.placement in ("workers", "ray") and _use_her(cfg, layout):
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
    cls = _algo_class(cfg)
    policy = "MultiInputPolicy" if layout.goal_env else "MlpPolicy"
    return cls(policy, vec_env, **model_kwargs(cfg, layout, run_dir))


# ---------------------------------------------------------------- logs


def _row_step(row: dict[str, Any], fields: tuple[str, ...]) -> int | None:
    """The step of a CSV row, or None for a row cut short (a process killed mid-write) or not a number."""
    if any(row.get(k) is None for k in fields):
        return None
    try:
        return int(float(row["step"]))
    except (KeyError, TypeError, ValueError):
        return None


class _CsvLog:
    """An append-only CSV file; on resume, rows after the checkpoint's step (and a last row cut short by a kill) are
    dropped first, and the kept rows replace the file atomically (``write_atomic``): a kill during a resume's
    rewrite loses no row."""

    def __init__(self, path: Path, fields: tuple[str, ...], *, keep_until_step: int | None) -> None:
        self.path = path
        self.fields = fields
        rows: list[dict[str, str]] = []
        if keep_until_step is not None and path.is_file():
            with open(path, newline="") as f:
                for r in csv.DictReader(f):
                    step = _row_step(r, fields)
                    if step is not None and step <= keep_until_step:
                        rows.append(r)
        text = io.StringIO(newline="")
        w = csv.DictWriter(text, fieldnames=list(fields))
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") for k in fields})
        write_atomic(path, text.getvalue().encode())
        self._f = open(path, "a", newline="")  # noqa: SIM115 (closed in close())
        self._w = csv.DictWriter(self._f, fieldnames=list(fields))

    def write(self, **row: Any) -> None:
        self._w.writerow(row)
        self._f.flush()

    def close(self) -> None:
        self._f.close()


def _make_callback(
    cfg: TrainConfig,
    run_dir: Path,
    layout: EnvLayout,
    eval_envs: list[tuple[str, str, gym.Env[Any, Any]]],
    episodes_log: _CsvLog,
    eval_log: _CsvLog,
    state: dict[str, Any],
    progress: bool,
) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback

    class TrainingCallback(BaseCallback):
        """Episode rows, success per env, progress bar, periodic evaluation and checkpoints."""

        def _on_training_start(self) -> None:
            self.windows: dict[str, collections.deque[bool]] = {
                lab: collections.deque(maxlen=50) for lab in layout.labels
            }
            self.bar = None
            self.last_step = self.num_timesteps
            if progress:
                from uniros_async._progress import progress_bar

                self.bar = progress_bar(
                    total=cfg.total_steps,
                    initial=self.num_timesteps,
                    unit="step",
                    desc=cfg.name,
                    mininterval=2.0,
                    dynamic_ncols=True,
                )

        def _on_step(self) -> bool:
            step = self.num_timesteps
            for done, info in zip(self.locals["dones"], self.locals["infos"], strict=True):
                if not done:
                    continue
                ep = info.get("episode", {})
                task = info.get("task", layout.labels[0])
                success = bool(info.get("is_success", False))
                episodes_log.write(
                    step=step,
                    task=task,
                    **{"return": round(float(ep.get("r", np.nan)), 4)},
                    length=int(ep.get("l", 0)),
                    success=int(success),
                )
                self.windows.setdefault(task, collections.deque(maxlen=50)).append(success)
                self.logger.record(f"train/success_rate/{task}", float(np.mean(self.windows[task])))
            if self.bar is not None:
                self.bar.update(1)
                if step % 200 == 0:
                    self.bar.set_postfix_str(
                        " ".join(f"{k}:{100 * np.mean(v):.0f}%" for k, v in self.windows.items() if v), refresh=False
                    )
            return True

        def _on_rollout_end(self) -> None:
            # here, not in _on_step: SB3 stores a step's transition after its callbacks ran, so a checkpoint
            # written at the end of the rollout holds every transition up to its step
            step = self.num_timesteps
            last, self.last_step = self.last_step, step
            if cfg.eval.every_steps and step // cfg.eval.every_steps > last // cfg.eval.every_steps:
                state["last_eval"] = self.run_eval(self.model, step)
            if cfg.checkpoint.every_steps and step // cfg.checkpoint.every_steps > last // cfg.checkpoint.every_steps:
                state["checkpoint"] = self.write_checkpoint(self.model, step)

        def _on_training_end(self) -> None:
            if self.bar is not None:
                self.bar.close()

        def run_eval(self, model: Any, step: int) -> list[EvalResult]:
            results = _run_eval(model, step, cfg, eval_envs, eval_log, self.logger)
            if self.bar is not None:
                self.bar.write(
                    f"[{cfg.name}] step {step}: "
                    + "; ".join(f"{r.label} {100 * r.success_rate:.0f}% len {r.mean_length:.1f}" for r in results)
                )
            state["last_eval_step"] = step
            return results

        def write_checkpoint(self, model: Any, step: int) -> Path:
            return _save(model, cfg, run_dir, layout, step)

    cb = TrainingCallback()
    return cb


def _run_eval(
    model: Any,
    step: int,
    cfg: TrainConfig,
    eval_envs: list[tuple[str, str, gym.Env[Any, Any]]],
    eval_log: _CsvLog,
    sb3_logger: Any,
) -> list[EvalResult]:
    """Evaluate on every eval env; rows to eval.csv, scalars to TensorBoard (when ``sb3_logger`` is given)."""
    results = []
    for label, env_id, env in eval_envs:
        r = evaluate_policy(model, env, cfg.eval.episodes, seed=cfg.seed + 10_000 + step, label=label, env_id=env_id)
        results.append(r)
        eval_log.write(
            step=step,
            task=label,
            success_rate=round(r.success_rate, 4),
            mean_return=round(r.mean_return, 4),
            mean_length=round(r.mean_length, 2),
            episodes=r.episodes,
        )
        if sb3_logger is not None:
            sb3_logger.record(f"eval/success_rate/{label}", r.success_rate)
            sb3_logger.record(f"eval/mean_return/{label}", r.mean_return)
            sb3_logger.record(f"eval/mean_ep_length/{label}", r.mean_length)
        logger.info("step %d eval %s", step, r.summary())
    return results


def _save(model: Any, cfg: TrainConfig, run_dir: Path, layout: EnvLayout, step: int) -> Path:
    meta = CheckpointMeta(
        step=step,
        obs_size=layout.obs_size,
        action_size=layout.action_size,
        goal_env=layout.goal_env,
        pad_to=layout.pad_to,
        task_id_size=layout.task_id_size,
        algo=type(model).__name__,
        labels=layout.labels,
        config=config_to_dict(cfg),
        drop_observation=tuple(cfg.drop_observation),
    )
    return save_checkpoint(model, run_dir, meta, keep=cfg.checkpoint.keep, replay_buffer=cfg.checkpoint.replay_buffer)


# ---------------------------------------------------------------- run


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM raises KeyboardInterrupt in the main thread (as Ctrl-C does), so the run stops the same way."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _set_torch_threads(n: int) -> None:
    import torch

    torch.set_num_threads(n)
    with contextlib.suppress(RuntimeError):  # may only be set once per process, before any inter-op work
        torch.set_num_interop_threads(n)


def train(cfg: TrainConfig, *, resume: bool = False, progress: bool | None = None) -> TrainResult:
    """Run (or, with ``resume``, continue) the training run ``cfg`` (see the module docstring).

    Raises:
        ConfigError: bad envs or settings, found before anything starts; or a fresh run in a directory that
            already holds checkpoints.
        CheckpointError: ``resume`` with no checkpoint, or one whose sizes differ from the envs (both named).
        TrainingInterrupted: Ctrl-C or SIGTERM; the last checkpoint is intact.
        WorkerError: a worker died (``placement: workers``); the last checkpoint is intact.
    """
    cfg.check_envs()
    run_dir = cfg.resolved_run_dir()
    ckpt: Path | None = None
    if resume:
        ckpt = latest_checkpoint(run_dir)
        if ckpt is None:
            raise CheckpointError(f"nothing to resume: {run_dir} has no complete checkpoint")
    elif latest_checkpoint(run_dir) is not None:
        raise ConfigError(
            f"{run_dir} already holds checkpoints of a run: resume it with --resume, or choose another name or run_dir"
        )
    run_dir.mkdir(parents=True, exist_ok=True)
    clean_partial(run_dir)
    _set_torch_threads(cfg.torch_threads)
    progress = cfg.progress_bar if progress is None else progress
    t0 = time.monotonic()

    env, layout = build_train_env(cfg)
    eval_envs: list[tuple[str, str, gym.Env[Any, Any]]] = []
    logs: list[_CsvLog] = []
    state: dict[str, Any] = {"checkpoint": ckpt}
    model: Any = None
    try:
        eval_envs = build_eval_envs(cfg, layout)
        if ckpt is not None:
            meta = read_meta(ckpt)
            check_sizes(meta, layout.obs_size, layout.action_size, layout.goal_env, f"the envs of {cfg.name}")
            cls = _algo_class(cfg)
            if meta.algo != cls.__name__:
                raise CheckpointError(f"{ckpt} was written by {meta.algo}; the config asks for {cls.__name__}")
            if meta.normalize_obs != cfg.normalize_obs:
                raise CheckpointError(
                    f"{ckpt} was trained with normalize_obs: {str(meta.normalize_obs).lower()}; the config says "
                    f"normalize_obs: {str(cfg.normalize_obs).lower()} (the policy's inputs would change meaning)"
                )
            vec = _vec_env(cfg, env, layout, resume_from=ckpt)
            model = cls.load(ckpt / "model.zip", env=vec, device="cpu", tensorboard_log=str(run_dir / "tb"))  # type: ignore[attr-defined]
            rows = load_replay_buffer(model, ckpt) if cfg.checkpoint.replay_buffer else 0
            model._last_obs = None  # the env is new: start a fresh episode instead of continuing a stale one
            start = int(model.num_timesteps)
            logger.info("resuming %s from %s (step %d, %d replay rows)", cfg.name, ckpt, start, rows)
        else:
            vec = _vec_env(cfg, env, layout)
            model = build_model(cfg, vec, layout, run_dir)
            start = 0
        # atomic: `--resume --run-dir` reads it back, also after a SIGKILL during this write
        write_atomic(run_dir / "config.yaml", yaml.safe_dump(config_to_dict(cfg), sort_keys=False).encode())
        keep = start if ckpt is not None else None
        episodes_log = _CsvLog(run_dir / "episodes.csv", EPISODE_FIELDS, keep_until_step=keep)
        logs.append(episodes_log)
        eval_log = _CsvLog(run_dir / "eval.csv", EVAL_FIELDS, keep_until_step=keep)
        logs.append(eval_log)
        callback = _make_callback(cfg, run_dir, layout, eval_envs, episodes_log, eval_log, state, progress)
        remaining = cfg.total_steps - start
        with _sigterm_as_interrupt():
            try:
                if remaining > 0:
                    model.learn(
                        total_timesteps=remaining,
                        callback=callback,
                        reset_num_timesteps=ckpt is None,
                        tb_log_name="td3",
                        log_interval=4,
                    )
                step = int(model.num_timesteps)
                if state.get("last_eval_step") != step:
                    sb3_logger = getattr(model, "_logger", None)
                    state["last_eval"] = _run_eval(model, step, cfg, eval_envs, eval_log, sb3_logger)
                    if sb3_logger is not None:
                        sb3_logger.dump(step)
                final_ckpt = state["checkpoint"]
                if final_ckpt is None or read_meta(final_ckpt).step != step:
                    final_ckpt = _save(model, cfg, run_dir, layout, step)
            except KeyboardInterrupt as exc:
                last = latest_checkpoint(run_dir)
                then = (
                    f"last checkpoint: {last}; continue with `uniros train --resume --run-dir {run_dir}`"
                    if last
                    else "no checkpoint was written yet: start the run again"
                )
                raise TrainingInterrupted(
                    f"{cfg.name} interrupted at step {int(model.num_timesteps)} ({exc or 'Ctrl-C'}); {then}", last
                ) from None
        results: list[EvalResult] = state["last_eval"]
        (run_dir / "final_eval.json").write_text(
            json.dumps({"step": step, "results": [r.to_dict() for r in results]}, indent=2)
        )
        return TrainResult(
            run_dir=run_dir, steps=step, checkpoint=final_ckpt, final_eval=results, wall_time_s=time.monotonic() - t0
        )
    finally:
        for log in logs:
            log.close()
        env.close()
        _close_all([e for _, _, e in eval_envs])
