"""What a training run's callback and ``train`` share (``Run``): the CSV logs (episodes.csv, eval.csv,
timing.csv), the evaluations and their records, the wall clock, and in concurrent runs the envs' timing windows
and timing.json."""

from __future__ import annotations

import collections
import csv
import io
import json
import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np

from uniros_async.training.alongside import Alongside
from uniros_async.training.checkpoint import write_atomic
from uniros_async.training.config import TrainConfig
from uniros_async.training.evaluate import EvalResult, evaluate_policy, evaluate_vec_policy

if TYPE_CHECKING:
    from uniros_async.training.build import EnvLayout
    from uniros_async.training.concurrent import ConcurrentVecEnv

__all__ = [
    "EPISODE_FIELDS",
    "EVAL_FIELDS",
    "TIMING_FIELDS",
    "CsvLog",
    "Run",
    "eval_seed",
    "record_eval",
    "restart_training_episodes",
    "results_text",
    "run_eval",
    "timing_summaries",
]

logger = logging.getLogger("uniros_async.training.recipes")


EPISODE_FIELDS = ("step", "task", "return", "length", "success", "wall_s")

EVAL_FIELDS = ("step", "task", "success_rate", "mean_return", "mean_length", "episodes", "wall_s")

TIMING_FIELDS = ("step", "wall_s", "task", "metric", "median_ms", "iqr_ms", "p99_ms", "count")


def _row_step(row: dict[str, Any], fields: tuple[str, ...]) -> int | None:
    """The step of a CSV row, or None for a row cut short (a process killed mid-write) or not a number. A column
    the file's header lacks (a run logged before it existed) does not count as cut short."""
    if any(v is None for v in row.values()):
        return None
    try:
        return int(float(row["step"]))
    except (KeyError, TypeError, ValueError):
        return None


class CsvLog:
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


class Run:
    """What the callback and ``train`` share: the logs, the evaluation, the wall clock and (concurrent runs) the
    envs' timing."""

    def __init__(
        self,
        cfg: TrainConfig,
        run_dir: Path,
        layout: EnvLayout,
        eval_envs: list[tuple[str, str, gym.Env[Any, Any]]],
        concurrent: ConcurrentVecEnv | None,
        episodes_log: CsvLog,
        eval_log: CsvLog,
        timing_log: CsvLog | None,
        wall_offset_s: float,
        alongside: Alongside | None = None,
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
        """Evaluate (``run_eval``) and remember the results."""
        self.last_eval = run_eval(model, step, self, sb3_logger, training_goes_on=training_goes_on)
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
            # whether the last evaluation alongside ran in the real-time class (Alongside.real_time_class)
            "eval_real_time": self.alongside is not None and self.alongside.real_time_class,
            "envs": {
                label: {"step_overruns": self.concurrent.step_overruns[label], **metrics}
                for label, metrics in timing_summaries(self.concurrent).items()
            },
        }
        if self.alongside is not None:  # the evaluation envs' timing, over every evaluation
            out["eval_envs"] = timing_summaries(self.alongside)
        (self.run_dir / "timing.json").write_text(json.dumps(out, indent=2))


def timing_summaries(venv: ConcurrentVecEnv | Alongside) -> dict[str, dict[str, dict[str, float | None]]]:
    """Every env's timing samples so far (``ConcurrentVecEnv.samples``) as summaries (median, IQR, p99, ... in ms)."""
    from uniros_async.stats import summary

    return {
        label: {metric: {k: _num(v) for k, v in summary(samples).items()} for metric, samples in metrics.items()}
        for label, metrics in venv.samples.items()
    }


def results_text(results: list[EvalResult]) -> str:
    """One evaluation's success and mean episode length per env, for a progress line."""
    return "; ".join(f"{r.label} {100 * r.success_rate:.0f}% len {r.mean_length:.1f}" for r in results)


def eval_seed(cfg: TrainConfig, step: int) -> int:
    """The seed of the evaluation at ``step`` (apart from the training envs' seeds)."""
    return cfg.seed + 10_000 + step


def run_eval(model: Any, step: int, run: Run, sb3_logger: Any, *, training_goes_on: bool = True) -> list[EvalResult]:
    """Evaluate on every eval env (concurrent runs: on the training envs, all at once, then, if
    ``training_goes_on``, reset them for training); rows to eval.csv, scalars to TensorBoard (when ``sb3_logger``
    is given)."""
    t0 = time.monotonic()
    seed = eval_seed(run.cfg, step)
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
            restart_training_episodes(model)
    else:
        results = [
            evaluate_policy(model, env, episodes, seed=seed, label=label, env_id=env_id)
            for label, env_id, env in run.eval_envs
        ]
    run.eval_s += time.monotonic() - t0
    record_eval(run, step, results, sb3_logger)
    return results


def record_eval(run: Run, step: int, results: list[EvalResult], sb3_logger: Any) -> None:
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


def restart_training_episodes(model: Any) -> None:
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
