"""SB3 recipes: TD3 for standard envs, TD3 + HerReplayBuffer for goal envs, single- or multi-task, with periodic
evaluation, TensorBoard logs, CSV learning curves and atomic checkpoints; ``train(cfg)`` runs one TrainConfig.

A run directory holds::

    config.yaml      the resolved config (``uniros train --resume --run-dir DIR`` reads it back)
    episodes.csv     one row per training episode: step, task, return, length, success, wall_s
    eval.csv         one row per evaluation and env: step, task, success_rate, mean_return, mean_length, episodes,
                     wall_s (seconds since training started, for curves against wall-clock time)
    final_eval.json  the last evaluation, per env
    timing.csv       (``concurrent`` runs) per timing window and env: the action cycle, actuator cycle and
                     observation age (median, IQR, p99, count, in ms) while training
    timing.json      (``concurrent`` runs) the same over the whole run, env steps, env steps per wall hour (and per
                     hour of training: without the evaluations that paused it), and with ``eval.alongside`` the
                     evaluation envs' timing over every evaluation
    tb/              TensorBoard (SB3's scalars plus train/success_rate/<env> and eval/*/<env>)
    checkpoints/     see checkpoint.py

Every env goes through ``TaskSamplerEnv`` (multitask.py): with one env it only tags infos; with several it is the
paper's Algorithm 1 (an env sampled per episode, one replay buffer, one policy). With ``concurrent: true`` the envs
instead run as one vector env over worker processes (concurrent.py): every env acts in every step, and the
evaluation steps them all at once, between two training steps, or, with ``eval.alongside``, on a second set of the
envs, in a process of its own with a copy of the policy, while training goes on (``alongside.Alongside``).

Interruption (Ctrl-C, SIGTERM, a dead worker) stops the run and leaves the last checkpoint intact;
``train(cfg, resume=True)`` continues from it (model, optimisers, step counter, action noise and replay buffer; the
env starts a fresh episode).

With ``normalize_obs`` the training VecEnv is wrapped in SB3's ``VecNormalize`` (observations only, statistics
updated as it steps): SB3 stores raw observations in the replay buffer and normalises them when it samples a batch
(HER relabels raw goals first), so relabelling and rewards never see normalised values. The statistics go into
every checkpoint (checkpoint.py), come back on resume, and every evaluation normalises with a frozen copy.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import gc
import json
import logging
import signal
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import yaml

from uniros_async.errors import ConfigError, TrainingInterrupted
from uniros_async.priority import freeze_heap
from uniros_async.training.alongside import Alongside, open_alongside, phase_bases, rank_bases
from uniros_async.training.build import (
    EnvLayout,
    algo_class,
    build_concurrent_env,
    build_eval_envs,
    build_model,
    build_train_env,
    close_all,
    real_time_actor,
    vec_env,
)
from uniros_async.training.checkpoint import (
    CheckpointError,
    CheckpointMeta,
    check_sizes,
    clean_partial,
    latest_checkpoint,
    load_replay_buffer,
    read_meta,
    save_checkpoint,
    write_atomic,
)
from uniros_async.training.config import TrainConfig, config_to_dict
from uniros_async.training.evaluate import EvalResult
from uniros_async.training.run_state import (
    EPISODE_FIELDS,
    EVAL_FIELDS,
    TIMING_FIELDS,
    CsvLog,
    Run,
    eval_seed,
    record_eval,
    results_text,
)

if TYPE_CHECKING:
    pass

__all__ = ["TrainResult", "TrainingInterrupted", "build_model", "build_train_env", "train"]

logger = logging.getLogger(__name__)

# vector steps between two reads of the envs' timing records in a concurrent run (200 s at 0.8 s per step); the
# read, a round trip per worker, falls between two steps whose period is in neither window
TIMING_WINDOW_STEPS = 250


@dataclasses.dataclass(frozen=True, kw_only=True)
class TrainResult:
    """What ``train`` returns."""

    run_dir: Path
    steps: int
    checkpoint: Path
    final_eval: list[EvalResult]
    wall_time_s: float


def _make_callback(run: Run, progress: bool) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback

    cfg, layout = run.cfg, run.layout

    class TrainingCallback(BaseCallback):
        """Episode rows, success per env, progress, periodic evaluation, timing windows and checkpoints."""

        def _on_training_start(self) -> None:
            self.bar = None
            self.targets_met = False  # eval.stop_success reached: the next step ends training
            self.last_step = self.num_timesteps
            self.vector_steps = 0
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
            wall = round(run.wall_s(), 1)
            for done, info in zip(self.locals["dones"], self.locals["infos"], strict=True):
                if not done:
                    continue
                ep = info.get("episode", {})
                task = info.get("task", layout.labels[0])
                success = bool(info.get("is_success", False))
                run.episodes_log.write(
                    step=step,
                    task=task,
                    **{"return": round(float(ep.get("r", np.nan)), 4)},
                    length=int(ep.get("l", 0)),
                    success=int(success),
                    wall_s=wall,
                )
                run.windows.setdefault(task, collections.deque(maxlen=50)).append(success)
                self.logger.record(f"train/success_rate/{task}", float(np.mean(run.windows[task])))
            if self.bar is not None:
                self.bar.update(step - self.bar.n)
                if step % 200 < layout.n_envs:
                    self.bar.set_postfix_str(
                        " ".join(f"{k}:{100 * np.mean(v):.0f}%" for k, v in run.windows.items() if v), refresh=False
                    )
            if self.targets_met:
                return False
            return cfg.max_wall_s is None or run.wall_s() < cfg.max_wall_s

        def _on_rollout_end(self) -> None:
            # here, not in _on_step: SB3 stores a step's transition after its callbacks ran, so a checkpoint
            # written at the end of the rollout holds every transition up to its step
            step = self.num_timesteps
            last, self.last_step = self.last_step, step
            self.vector_steps += 1
            if run.concurrent is not None and self.vector_steps % TIMING_WINDOW_STEPS == 0:
                self.write(run.progress_line(step, run.timing(step)))
            if run.alongside is not None:
                self.take_alongside(step)
            if cfg.eval.every_steps and step // cfg.eval.every_steps > last // cfg.eval.every_steps:
                if run.alongside is not None:
                    run.alongside.request(self.model, step, cfg.eval.episodes, eval_seed(cfg, step))
                else:
                    self.check_targets(step, self.run_eval(self.model, step))
            if cfg.checkpoint.every_steps and step // cfg.checkpoint.every_steps > last // cfg.checkpoint.every_steps:
                run.checkpoint = _save(self.model, cfg, run.run_dir, layout, step)

        def _on_training_end(self) -> None:
            if self.bar is not None:
                self.bar.close()

        def write(self, line: str) -> None:
            from tqdm import tqdm

            tqdm.write(line, file=sys.stderr) if self.bar is None else self.bar.write(line, file=sys.stderr)

        def check_targets(self, step: int, results: list[EvalResult]) -> None:
            target = cfg.eval.stop_success
            if target is not None and results and all(r.success_rate >= target for r in results):
                self.targets_met = True
                self.write(
                    f"[{cfg.name}] step {step}, {run.wall_s() / 60:.1f} min: every env at {100 * target:.0f} % "
                    "or above (eval.stop_success): training stops"
                )

        def take_alongside(self, step: int) -> None:
            assert run.alongside is not None
            done = run.alongside.take(self.model, step, cfg.eval.episodes, eval_seed(cfg, step))
            if done is None:
                return
            at, took_s, results = done
            record_eval(run, at, results, self.logger)
            run.last_eval, run.last_eval_step = results, at
            self.write(
                f"[{cfg.name}] step {step}, {run.wall_s() / 60:.1f} min: evaluated alongside training "
                f"(policy of step {at}, {took_s:.0f} s): " + results_text(results)
            )
            self.check_targets(step, results)

        def run_eval(self, model: Any, step: int) -> list[EvalResult]:
            results = run.evaluate(model, step, self.logger)
            if progress or run.concurrent is not None:
                self.write(f"[{cfg.name}] step {step}, {run.wall_s() / 60:.1f} min: " + results_text(results))
            return results

    return TrainingCallback()


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


@contextlib.contextmanager
def _frozen_heap() -> Iterator[None]:
    """Set-up done (envs, model, logs): collect, then move everything the agent process holds out of the cyclic
    collector's reach (``priority.freeze_heap``, as worker processes do after theirs), so that a full collection
    while training walks only what training made, not the modules, envs and model, and the acting thread that
    triggers it waits less. Unfrozen after, unless something had frozen the heap before."""
    before = gc.get_freeze_count()
    freeze_heap()
    try:
        yield
    finally:
        if before == 0:
            gc.unfreeze()


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

    env: Any
    if cfg.concurrent:
        n_envs = len(cfg.env_specs())
        if cfg.eval.alongside:
            rank = cfg.eval.alongside_rank
            env, layout = build_concurrent_env(
                cfg, rt_rank_base=rank_bases(rank, n_envs)[0], loop_phase_base=phase_bases(rank, n_envs)[0]
            )
        else:
            env, layout = build_concurrent_env(cfg)
    else:
        env, layout = build_train_env(cfg)
        if cfg.record is not None:  # every training step to MCAP (bag/episodes.py)
            from uniros_async.bag.episodes import RecordEpisodes

            rec = cfg.record
            path = rec.path or run_dir / "episodes.mcap"
            env = RecordEpisodes(env, path, episodes_per_file=rec.episodes_per_file, compression=rec.compression)
    eval_envs: list[tuple[str, str, gym.Env[Any, Any]]] = []
    alongside: Alongside | None = None
    logs: list[CsvLog] = []
    model: Any = None
    try:
        if not cfg.concurrent:
            eval_envs = build_eval_envs(cfg, layout)
        elif cfg.eval.alongside:
            alongside = open_alongside(
                cfg.env_specs(),
                real_time=real_time_actor(cfg),
                torch_threads=cfg.torch_threads,
                rank=cfg.eval.alongside_rank,
                phase=cfg.eval.alongside_phase,
                task_id=cfg.task_id_in_obs,
            )
        if ckpt is not None:
            meta = read_meta(ckpt)
            check_sizes(meta, layout.obs_size, layout.action_size, layout.goal_env, f"the envs of {cfg.name}")
            cls = algo_class(cfg)
            if meta.algo != cls.__name__:
                raise CheckpointError(f"{ckpt} was written by {meta.algo}; the config asks for {cls.__name__}")
            if meta.normalize_obs != cfg.normalize_obs:
                raise CheckpointError(
                    f"{ckpt} was trained with normalize_obs: {str(meta.normalize_obs).lower()}; the config says "
                    f"normalize_obs: {str(cfg.normalize_obs).lower()} (the policy's inputs would change meaning)"
                )
            vec = vec_env(cfg, env, layout, resume_from=ckpt)
            model = cls.load(ckpt / "model.zip", env=vec, device="cpu", tensorboard_log=str(run_dir / "tb"))  # type: ignore[attr-defined]
            rows = load_replay_buffer(model, ckpt) if cfg.checkpoint.replay_buffer else 0
            model._last_obs = None  # the env is new: start a fresh episode instead of continuing a stale one
            start = int(model.num_timesteps)
            logger.info("resuming %s from %s (step %d, %d replay rows)", cfg.name, ckpt, start, rows)
        else:
            vec = vec_env(cfg, env, layout)
            model = build_model(cfg, vec, layout, run_dir)
            start = 0
        # atomic: `--resume --run-dir` reads it back, also after a SIGKILL during this write
        write_atomic(run_dir / "config.yaml", yaml.safe_dump(config_to_dict(cfg), sort_keys=False).encode())
        keep = start if ckpt is not None else None
        episodes_log = CsvLog(run_dir / "episodes.csv", EPISODE_FIELDS, keep_until_step=keep)
        logs.append(episodes_log)
        eval_log = CsvLog(run_dir / "eval.csv", EVAL_FIELDS, keep_until_step=keep)
        logs.append(eval_log)
        timing_log = None
        if cfg.concurrent:
            timing_log = CsvLog(run_dir / "timing.csv", TIMING_FIELDS, keep_until_step=keep)
            logs.append(timing_log)
        run = Run(
            cfg,
            run_dir,
            layout,
            eval_envs,
            env if cfg.concurrent else None,
            episodes_log,
            eval_log,
            timing_log,
            wall_offset_s=max([0.0, *episodes_log.kept_wall_s, *eval_log.kept_wall_s]),
            alongside=alongside,
        )
        run.checkpoint = ckpt
        callback = _make_callback(run, progress)
        remaining = cfg.total_steps - start
        with _sigterm_as_interrupt(), _frozen_heap():
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
                final_n = cfg.eval.final_episodes
                if run.last_eval_step != step or (final_n is not None and final_n != cfg.eval.episodes):
                    sb3_logger = getattr(model, "_logger", None)
                    run.evaluate(model, step, sb3_logger, training_goes_on=False)
                    if sb3_logger is not None:
                        sb3_logger.dump(step)
                final_ckpt = run.checkpoint
                if final_ckpt is None or read_meta(final_ckpt).step != step:
                    final_ckpt = _save(model, cfg, run_dir, layout, step)
                run.write_timing_summary(step)
            except KeyboardInterrupt as exc:
                with contextlib.suppress(Exception):  # the run's timing so far; the interruption is what to report
                    run.write_timing_summary(int(model.num_timesteps))
                last = latest_checkpoint(run_dir)
                then = (
                    f"last checkpoint: {last}; continue with `uniros train --resume --run-dir {run_dir}`"
                    if last
                    else "no checkpoint was written yet: start the run again"
                )
                raise TrainingInterrupted(
                    f"{cfg.name} interrupted at step {int(model.num_timesteps)} ({str(exc) or 'Ctrl-C'}); {then}", last
                ) from None
        results: list[EvalResult] = run.last_eval
        (run_dir / "final_eval.json").write_text(
            json.dumps({"step": step, "results": [r.to_dict() for r in results]}, indent=2)
        )
        return TrainResult(
            run_dir=run_dir, steps=step, checkpoint=final_ckpt, final_eval=results, wall_time_s=time.monotonic() - t0
        )
    finally:
        for log in logs:
            log.close()
        try:
            if alongside is not None:
                alongside.close()
        finally:
            env.close()
        close_all([e for _, _, e in eval_envs])
