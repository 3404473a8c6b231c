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
envs, on a thread of its own with a copy of the policy, while training goes on (``_Alongside``).

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
import csv
import dataclasses
import io
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

from uniros_async.envs.config import EnvConfig
from uniros_async.errors import ConfigError, TrainingInterrupted, UnirosError
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
from uniros_async.training.evaluate import EvalResult, evaluate_policy, evaluate_vec_policy, frozen_obs_stats
from uniros_async.training.multitask import TaskIdObservation, TaskSamplerEnv, build_env, space_sizes

if TYPE_CHECKING:
    from uniros_async.training.concurrent import ConcurrentVecEnv

__all__ = ["TrainResult", "TrainingInterrupted", "build_model", "build_train_env", "train"]

logger = logging.getLogger(__name__)

EPISODE_FIELDS = ("step", "task", "return", "length", "success", "wall_s")
EVAL_FIELDS = ("step", "task", "success_rate", "mean_return", "mean_length", "episodes", "wall_s")
TIMING_FIELDS = ("step", "wall_s", "task", "metric", "median_ms", "iqr_ms", "p99_ms", "count")
# vector steps between two reads of the envs' timing records in a concurrent run (200 s at 0.8 s per step); the
# read, a round trip per worker, falls between two steps whose period is in neither window
TIMING_WINDOW_STEPS = 250
# how long closing waits for the evaluation thread of eval.alongside: it checks its stop event before every step,
# and a step waits at most for its action cycle or the workers' step deadline
_ALONGSIDE_JOIN_S = 60.0


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
    n_envs: int = 1


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


def build_concurrent_env(cfg: TrainConfig) -> tuple[ConcurrentVecEnv, EnvLayout]:
    """The training envs as one ConcurrentVecEnv over worker processes (``concurrent: true``) and their layout.

    Raises:
        ConfigError: unknown ids or arguments, or mixed goal and standard envs.
        WorkerError: a worker failed to start.
    """
    from uniros_async.training.concurrent import open_concurrent_env

    venv = open_concurrent_env(cfg.env_specs())
    try:
        goal = isinstance(venv.observation_space, gym.spaces.Dict)
        box = venv.observation_space["observation"] if goal else venv.observation_space  # type: ignore[index]
        obs_size, act_size = int(box.shape[0]), int(venv.action_space.shape[0])  # type: ignore[index]
    except BaseException:
        venv.close()
        raise
    layout = EnvLayout(
        pad_to=(obs_size, act_size) if len(cfg.envs) > 1 else None,
        task_id_size=0,
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


def _vec_env(cfg: TrainConfig, env: Any, layout: EnvLayout, resume_from: Path | None = None) -> Any:
    """The training VecEnv: Monitor, DummyVecEnv, local HER rewards for workers, and with ``normalize_obs`` a
    VecNormalize on top (fresh, or the statistics of the checkpoint ``resume_from``)."""
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor, VecNormalize

    if cfg.concurrent:
        vec: Any = VecMonitor(env, info_keywords=("is_success",))
    else:
        vec = DummyVecEnv([lambda: Monitor(env, info_keywords=("is_success",))])
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
    """The step of a CSV row, or None for a row cut short (a process killed mid-write) or not a number. A column
    the file's header lacks (a run logged before it existed) does not count as cut short."""
    if any(v is None for v in row.values()):
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
        self.kept_wall_s = [float(r["wall_s"]) for r in rows if r.get("wall_s")]
        """The ``wall_s`` of the rows kept (a resumed run's wall clock goes on from their largest)."""
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


class _FrozenPolicy:
    """A copy of a model's policy (and observation statistics) at one step, for an evaluation on another thread:
    the learner goes on updating the model's networks while it acts."""

    def __init__(self, model: Any) -> None:
        import copy

        paused = getattr(model, "learner_paused", contextlib.nullcontext)
        with paused():  # AsyncTD3: between two updates, so the copy is one consistent set of weights
            self.policy = copy.deepcopy(model.policy)
        self.policy.set_training_mode(False)
        live = model.get_vec_normalize_env()
        self.stats = None if live is None else frozen_obs_stats(live)

    def predict(self, observation: Any, deterministic: bool = True) -> tuple[np.ndarray, None]:
        """The copied policy's actions (SB3's ``predict``)."""
        actions, _ = self.policy.predict(observation, deterministic=deterministic)
        return actions, None

    def get_vec_normalize_env(self) -> Any:
        """The observation statistics at the copy's step (frozen), or None."""
        return self.stats


class _Alongside:
    """The periodic evaluation of ``eval.alongside``: a second ConcurrentVecEnv of the training envs, stepped by a
    thread of its own (one evaluation at a time) while training goes on. ``request`` starts an evaluation with a
    copy of the policy (or, while one runs, marks the next as due), ``take`` hands over a finished one's results,
    ``close`` stops a running one (within one action cycle) and closes the envs."""

    def __init__(self, venv: ConcurrentVecEnv, env_ids: list[str]) -> None:
        self.venv = venv
        self.env_ids = env_ids
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._outcome: tuple[int, float, list[EvalResult] | BaseException] | None = None
        self._due = False  # an evaluation fell due while another ran

    def busy(self) -> bool:
        """Whether an evaluation runs (or has ended and waits for ``take``)."""
        return self._thread is not None

    def request(self, model: Any, step: int, episodes: int, seed: int) -> None:
        """Evaluate the policy as it is at ``step``, now or (one running) when the running one ends."""
        if self.busy():
            self._due = True
            return
        policy = _FrozenPolicy(model)
        t0 = time.monotonic()

        def run() -> None:
            try:
                out: list[EvalResult] | BaseException = self.evaluate(policy, episodes, seed, self._stop)
            except BaseException as exc:  # noqa: BLE001 - handed to the training thread by take()
                out = exc
            self._outcome = (step, time.monotonic() - t0, out)

        self._thread = threading.Thread(target=run, name=f"eval-alongside-{step}", daemon=True)
        self._thread.start()

    def evaluate(self, policy: Any, episodes: int, seed: int, stop: threading.Event | None = None) -> list[EvalResult]:
        """One evaluation of ``policy`` on the envs (in the calling thread), their action-cycle timing kept."""
        results = evaluate_vec_policy(
            policy, self.venv, episodes, self.venv.labels, seed=seed, env_ids=self.env_ids, stop=stop
        )
        self.venv.timing_window()  # the evaluation's action cycles, kept in venv.samples for timing.json
        return results

    def take(self, model: Any, step: int, episodes: int, seed: int) -> tuple[int, float, list[EvalResult]] | None:
        """A finished evaluation's (step, seconds it took, results), or None; starts the one that fell due meanwhile
        (with the policy at ``step``). Raises what the evaluation raised (e.g. WorkerError)."""
        thread = self._thread
        if thread is None or thread.is_alive():
            return None
        thread.join()
        self._thread = None
        assert self._outcome is not None
        done_step, took_s, out = self._outcome
        self._outcome = None
        if isinstance(out, BaseException):
            raise out
        if self._due:
            self._due = False
            self.request(model, step, episodes, seed)
        return done_step, took_s, out

    def cancel(self) -> None:
        """Stop a running evaluation (it ends before its next step, within an action cycle) and drop it."""
        self._due = False
        thread = self._thread
        if thread is not None:
            self._stop.set()
            thread.join(_ALONGSIDE_JOIN_S)
            if thread.is_alive():
                raise UnirosError(f"the evaluation alongside training did not stop within {_ALONGSIDE_JOIN_S:.0f} s")
            self._thread = None
            self._outcome = None
            self._stop.clear()

    def close(self) -> None:
        """``cancel`` and close the envs."""
        try:
            self.cancel()
        finally:
            self.venv.close()


class _Run:
    """What the callback and ``train`` share: the logs, the evaluation, the wall clock and (concurrent runs) the
    envs' timing."""

    def __init__(
        self,
        cfg: TrainConfig,
        run_dir: Path,
        layout: EnvLayout,
        eval_envs: list[tuple[str, str, gym.Env[Any, Any]]],
        concurrent: ConcurrentVecEnv | None,
        episodes_log: _CsvLog,
        eval_log: _CsvLog,
        timing_log: _CsvLog | None,
        wall_offset_s: float,
        alongside: _Alongside | None = None,
    ) -> None:
        self.cfg = cfg
        self.alongside = alongside
        self.run_dir = run_dir
        self.layout = layout
        self.eval_envs = eval_envs
        self.concurrent = concurrent
        self.episodes_log = episodes_log
        self.eval_log = eval_log
        self.timing_log = timing_log
        self.wall_offset_s = wall_offset_s
        self.t0 = time.monotonic()
        self.eval_s = 0.0  # wall time spent evaluating
        self.checkpoint: Path | None = None
        self.last_eval: list[EvalResult] = []
        self.last_eval_step: int | None = None
        self.windows: dict[str, collections.deque[bool]] = {lab: collections.deque(maxlen=50) for lab in layout.labels}

    def wall_s(self) -> float:
        """Seconds of training so far (on resume, counted on from the kept rows)."""
        return self.wall_offset_s + time.monotonic() - self.t0

    def evaluate(self, model: Any, step: int, sb3_logger: Any, *, training_goes_on: bool = True) -> list[EvalResult]:
        """Evaluate (``_run_eval``) and remember the results."""
        self.last_eval = _run_eval(model, step, self, sb3_logger, training_goes_on=training_goes_on)
        self.last_eval_step = step
        return self.last_eval

    def timing(self, step: int) -> dict[str, dict[str, list[float]]]:
        """Close the concurrent envs' timing window: one timing.csv row per env and metric."""
        if self.concurrent is None or self.timing_log is None:
            return {}
        from uniros_async.stats import summary

        window = self.concurrent.timing_window()
        wall = round(self.wall_s(), 1)
        for label, metrics in window.items():
            for metric, samples in metrics.items():
                if not samples:  # a window closed right after another (an evaluation after a progress line)
                    continue
                st = summary(samples)
                self.timing_log.write(
                    step=step,
                    wall_s=wall,
                    task=label,
                    metric=metric,
                    median_ms=_num(st["p50"]),
                    iqr_ms=_num(st["iqr"]),
                    p99_ms=_num(st["p99"]),
                    count=int(st["count"]),
                )
        return window

    def progress_line(self, step: int, window: dict[str, dict[str, list[float]]]) -> str:
        """One line: steps, wall time, env steps per hour, success per env (last 50 training episodes), action
        cycle per env (this window's median and IQR)."""
        from uniros_async.stats import summary

        wall = self.wall_s()
        per_h = step / wall * 3600 if wall > 0 else 0.0
        parts = [f"[{self.cfg.name}] step {step}, {wall / 60:.1f} min, {per_h:.0f} env steps/h"]
        for label in self.layout.labels:
            w = self.windows.get(label)
            ok = f"{100 * np.mean(w):.0f}%" if w else "-"
            cyc = summary(window.get(label, {}).get("action_cycle", []))
            cycle = f", cycle {cyc['p50']:.1f}/{cyc['iqr']:.2f} ms" if cyc["count"] else ""
            parts.append(f"{label} {ok}{cycle}")
        return "; ".join(parts)

    def write_timing_summary(self, step: int) -> None:
        """timing.json: env steps, wall time, env steps per wall hour and each env's timing over the run."""
        if self.concurrent is None:
            return
        wall = self.wall_s()
        train_s = wall - self.eval_s
        out: dict[str, Any] = {
            "env_steps": step,
            "wall_s": round(wall, 1),
            "eval_wall_s": round(self.eval_s, 1),
            "env_steps_per_wall_hour": round(step / wall * 3600, 1) if wall > 0 else None,
            # the same without the evaluations' wall time (they step the same envs, but store nothing)
            "env_steps_per_training_hour": round(step / train_s * 3600, 1) if train_s > 0 else None,
            "learner": self.cfg.learner,
            "eval_alongside": self.alongside is not None,
            "envs": {
                label: {"step_overruns": self.concurrent.step_overruns[label], **metrics}
                for label, metrics in _timing_summaries(self.concurrent).items()
            },
        }
        if self.alongside is not None:  # the evaluation envs' timing, over every evaluation
            out["eval_envs"] = _timing_summaries(self.alongside.venv)
        (self.run_dir / "timing.json").write_text(json.dumps(out, indent=2))


def _timing_summaries(venv: ConcurrentVecEnv) -> dict[str, dict[str, dict[str, float | None]]]:
    """Every env's timing samples so far (``ConcurrentVecEnv.samples``) as summaries (median, IQR, p99, ... in ms)."""
    from uniros_async.stats import summary

    return {
        label: {metric: {k: _num(v) for k, v in summary(samples).items()} for metric, samples in metrics.items()}
        for label, metrics in venv.samples.items()
    }


def _results_text(results: list[EvalResult]) -> str:
    """One evaluation's success and mean episode length per env, for a progress line."""
    return "; ".join(f"{r.label} {100 * r.success_rate:.0f}% len {r.mean_length:.1f}" for r in results)


def _eval_seed(cfg: TrainConfig, step: int) -> int:
    """The seed of the evaluation at ``step`` (apart from the training envs' seeds)."""
    return cfg.seed + 10_000 + step


def _run_eval(model: Any, step: int, run: _Run, sb3_logger: Any, *, training_goes_on: bool = True) -> list[EvalResult]:
    """Evaluate on every eval env (concurrent runs: on the training envs, all at once, then, if
    ``training_goes_on``, reset them for training); rows to eval.csv, scalars to TensorBoard (when ``sb3_logger``
    is given)."""
    t0 = time.monotonic()
    seed = _eval_seed(run.cfg, step)
    episodes = run.cfg.eval.episodes
    if not training_goes_on and run.cfg.eval.final_episodes is not None:
        episodes = run.cfg.eval.final_episodes
    if run.alongside is not None and not training_goes_on:  # the final evaluation, on the evaluation envs
        run.alongside.cancel()  # a periodic one still running: superseded by this one
        run.timing(step)
        results = run.alongside.evaluate(model, episodes, seed)
    elif run.concurrent is not None:
        run.timing(step)  # the training window ends here: the evaluation's steps are not training's
        results = evaluate_vec_policy(
            model,
            run.concurrent.venv,
            episodes,
            run.concurrent.labels,
            seed=seed,
            env_ids=[i for _, i, _ in run.cfg.env_specs()],
        )
        if training_goes_on:
            _restart_training_episodes(model)
    else:
        results = [
            evaluate_policy(model, env, episodes, seed=seed, label=label, env_id=env_id)
            for label, env_id, env in run.eval_envs
        ]
    run.eval_s += time.monotonic() - t0
    _record_eval(run, step, results, sb3_logger)
    return results


def _record_eval(run: _Run, step: int, results: list[EvalResult], sb3_logger: Any) -> None:
    """An evaluation's rows to eval.csv (``wall_s``: now, when its results are known), scalars to TensorBoard."""
    wall = round(run.wall_s(), 1)
    for r in results:
        run.eval_log.write(
            step=step,
            task=r.label,
            success_rate=round(r.success_rate, 4),
            mean_return=round(r.mean_return, 4),
            mean_length=round(r.mean_length, 2),
            episodes=r.episodes,
            wall_s=wall,
        )
        if sb3_logger is not None:
            sb3_logger.record(f"eval/success_rate/{r.label}", r.success_rate)
            sb3_logger.record(f"eval/mean_return/{r.label}", r.mean_return)
            sb3_logger.record(f"eval/mean_ep_length/{r.label}", r.mean_length)
        logger.info("step %d eval %s", step, r.summary())


def _num(x: float) -> float | None:
    return round(float(x), 4) if np.isfinite(x) else None


def _restart_training_episodes(model: Any) -> None:
    """After an evaluation on the training envs: reset them (through the model's wrappers, so VecMonitor's
    episode counters start afresh) and start the next transition from there."""
    env = model.get_env()
    model._last_obs = env.reset()
    vec_norm = model.get_vec_normalize_env()
    if vec_norm is not None:
        model._last_original_obs = vec_norm.get_original_obs()
    model._last_episode_starts = np.ones((env.num_envs,), dtype=bool)
    if model.action_noise is not None:
        model.action_noise.reset()


def _make_callback(run: _Run, progress: bool) -> Any:
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
                    run.alongside.request(self.model, step, cfg.eval.episodes, _eval_seed(cfg, step))
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
            done = run.alongside.take(self.model, step, cfg.eval.episodes, _eval_seed(cfg, step))
            if done is None:
                return
            at, took_s, results = done
            _record_eval(run, at, results, self.logger)
            run.last_eval, run.last_eval_step = results, at
            self.write(
                f"[{cfg.name}] step {step}, {run.wall_s() / 60:.1f} min: evaluated alongside training "
                f"(policy of step {at}, {took_s:.0f} s): " + _results_text(results)
            )
            self.check_targets(step, results)

        def run_eval(self, model: Any, step: int) -> list[EvalResult]:
            results = run.evaluate(model, step, self.logger)
            if progress or run.concurrent is not None:
                self.write(f"[{cfg.name}] step {step}, {run.wall_s() / 60:.1f} min: " + _results_text(results))
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
        env, layout = build_concurrent_env(cfg)
    else:
        env, layout = build_train_env(cfg)
    eval_envs: list[tuple[str, str, gym.Env[Any, Any]]] = []
    alongside: _Alongside | None = None
    logs: list[_CsvLog] = []
    model: Any = None
    try:
        if not cfg.concurrent:
            eval_envs = build_eval_envs(cfg, layout)
        elif cfg.eval.alongside:
            eval_venv, _ = build_concurrent_env(cfg)
            alongside = _Alongside(eval_venv, [i for _, i, _ in cfg.env_specs()])
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
        timing_log = None
        if cfg.concurrent:
            timing_log = _CsvLog(run_dir / "timing.csv", TIMING_FIELDS, keep_until_step=keep)
            logs.append(timing_log)
        run = _Run(
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
        _close_all([e for _, _, e in eval_envs])
