"""The agent process of `uniros train` in real time: the action cycles of the evaluation arms of `eval.alongside` and
of the training arms, and the heap frozen after set-up against unfrozen, each in the same run; the runs alternate
which set of arms ranks higher (`eval.alongside_rank`), the evaluation arms' phase and the loops' tick phases.

Four arms train (rx200 and ned2, sim and emulated real, on the wall clock, as configs/realtime_multitask_async.yaml
has them, at a shorter action cycle so that a run gathers enough cycles) with the asynchronous learner, and four more
are evaluated alongside, almost without a pause (short episodes, an evaluation every few vector steps).

- **Evaluation arms**: four, in the evaluation process (`training/eval_process.py`, what `train` does). Printed per
  arm: the action cycle's median and IQR over the evaluations (goal: IQR < 1 ms), beside the training arms' over
  the run. With `--thread` the evaluations alternate with a second set of four evaluation arms in worker processes
  of the agent process, stepped by a thread of the agent process in the real-time class with a frozen copy of the
  policy (`_InThread` below: the path `train` had before), which then see the same moments of the host's load and
  of the learner's updates; those four more arms load the host beyond what `train` runs.
- **Which arms rank higher**: the runs alternate `eval.alongside_rank`: `training` (the training arms' env loops
  ranked above the evaluation process's, `train`'s default) and `evaluation` (the reverse); every row names its
  order. The in-thread path's arms rank as the lower set in both.
- **Phase**: the runs also alternate `eval.alongside_phase`: 0 (both sets' steps, and the policy's actions for
  them, fall due on the same instants) and 0.5 (`train`'s default: the evaluation arms' steps half a cycle after
  the training arms'); the in-thread path's arms take the same phase.
- **Tick phases** (`--layouts`): `higher-first` (what `train` does, `alongside.phase_bases`: the loops of the set
  that ranks higher tick first, the other set's in the milliseconds after) against `by-rank` (each loop's tick
  phase its real-time rank, `make_vec`'s default: the set that ranks higher ticks last). Every loop ticks every
  period, so the two sets' ticks meet in every period whatever the evaluation phase.
- **Frozen heap**: when the learner starts (the set-up done, the heap frozen by `train`), one full collection is
  timed with the heap frozen and one with it unfrozen (then frozen again), back to back; and the full (generation
  2) collections while the learner learns are counted and timed (`gc.callbacks`).

    python benchmarks/agent_realtime.py                 # one 150 s run per order, phase and layout: about 27 minutes
    python benchmarks/agent_realtime.py --orders training --phases 0.5 --runs 2 --json out.json

`--json` writes the action-cycle rows of `uniros bench report`'s latency table (every run's samples pooled per arm,
path and order), the load average seen during the runs, and every run's raw figures.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import gc
import json
import os
import platform
import statistics
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from uniros_async.errors import ConfigError
from uniros_async.priority import real_time_thread
from uniros_async.stats import summary
from uniros_async.training import recipes
from uniros_async.training.alongside import RANKS, Alongside, phased, rank_bases
from uniros_async.training.async_td3 import AsyncTD3
from uniros_async.training.concurrent import TIMING_METRICS, open_concurrent_env
from uniros_async.training.config import train_config_from_dict
from uniros_async.training.eval_process import open_eval_process
from uniros_async.training.evaluate import EvalResult, evaluate_vec_policy, frozen_obs_stats

CYCLE_S = 0.4
EPISODE_STEPS = 10
PROCESS, THREAD, TRAINING = "eval process (rt)", "eval thread (rt)", "training (acting thread, rt)"
ORDERS = RANKS  # eval.alongside_rank: which set of arms' loops ranks higher
LAYOUTS = ("higher-first", "by-rank")  # the loops' tick phases: alongside.phase_bases, or each loop's rank


def _config(run_dir: Path, seconds: float, order: str, phase: float) -> Any:
    return train_config_from_dict(
        {
            "name": run_dir.name,
            "run_dir": str(run_dir),
            "total_steps": 1_000_000,
            "max_wall_s": seconds,
            "envs": [
                {"id": "uniros/Rx200Reach-v0", "name": "rx200_sim"},
                {"id": "uniros/Rx200Reach-v0", "name": "rx200_real", "kwargs": {"robot": "emulated-real"}},
                {"id": "uniros/Ned2Reach-v0", "name": "ned2_sim", "kwargs": {"delta_coeff": 0.02}},
                {"id": "uniros/Ned2Reach-v0", "name": "ned2_real", "kwargs": {"robot": "emulated-real"}},
            ],
            "env_defaults": {
                "clock": "wall",
                "action_cycle_s": CYCLE_S,
                "reward_type": "dense",
                "action_mode": "delta",
                "max_episode_steps": EPISODE_STEPS,
            },
            "placement": "workers",
            "concurrent": True,
            "learner": "async",
            "async_learner": {"updates_per_step": 1.0},
            "td3": {"learning_rate": 1.0e-3, "batch_size": 100, "learning_starts": 40, "action_noise_std": 0.01},
            # an evaluation every 4 vector steps: one episode per env, EPISODE_STEPS cycles, then the next is due
            "eval": {
                "every_steps": 16,
                "episodes": 1,
                "final_episodes": 1,
                "alongside": True,
                "alongside_rank": order,
                "alongside_phase": phase,
            },
            "checkpoint": {"every_steps": 0},
            "torch_threads": 1,
            "progress_bar": False,
        }
    )


class _InThread:
    """The evaluation arms in worker processes of the agent process, evaluated on a thread of it in the real-time
    class with a copy of the policy taken between two learner updates (``Alongside``'s API, one at a time)."""

    def __init__(self, specs: Sequence[tuple[str, str, dict[str, Any]]], real_time: bool) -> None:
        self.venv = open_concurrent_env(specs)
        self.env_ids = [env_id for _, env_id, _ in specs]
        self.real_time = real_time
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._outcome: tuple[int, float, list[EvalResult] | BaseException] | None = None

    def request(self, model: Any, step: int, episodes: int, seed: int) -> None:
        with model.learner_paused():
            policy = copy.deepcopy(model.policy)
        policy.set_training_mode(False)
        live = model.get_vec_normalize_env()
        frozen = _Frozen(policy, None if live is None else frozen_obs_stats(live))
        t0 = time.monotonic()

        def run() -> None:
            out: list[EvalResult] | BaseException
            try:
                with real_time_thread() if self.real_time else contextlib.nullcontext(False):
                    out = evaluate_vec_policy(
                        frozen, self.venv, episodes, self.venv.labels, seed=seed, env_ids=self.env_ids, stop=self._stop
                    )
                self.venv.timing_window()
            except BaseException as exc:  # noqa: BLE001 - handed over by take()
                out = exc
            self._outcome = (step, time.monotonic() - t0, out)

        self._thread = threading.Thread(target=run, name=f"eval-in-thread-{step}", daemon=True)
        self._thread.start()

    def take(self, model: Any, step: int, episodes: int, seed: int) -> tuple[int, float, list[EvalResult]] | None:
        if self._thread is None or self._thread.is_alive():
            return None
        self._thread.join()
        self._thread = None
        assert self._outcome is not None
        done_step, took_s, out = self._outcome
        if isinstance(out, BaseException):
            raise out
        return done_step, took_s, out

    def cancel(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join(60.0)
            self._thread = None
            self._stop.clear()

    def close(self) -> None:
        try:
            self.cancel()
        finally:
            self.venv.close()


class _Frozen:
    def __init__(self, policy: Any, stats: Any) -> None:
        self.policy, self.stats = policy, stats

    def predict(self, observation: Any, deterministic: bool = True) -> tuple[Any, None]:
        return self.policy.predict(observation, deterministic=deterministic)[0], None

    def get_vec_normalize_env(self) -> Any:
        return self.stats


class _Alternating:
    """``Alongside``'s API over the evaluation process and the in-thread path: the periodic evaluations take turns,
    the final one runs in the evaluation process; the load average is read at every ``take``."""

    def __init__(self, process: Any, in_thread: _InThread | None, loads: list[float]) -> None:
        self.process, self.in_thread, self.loads = process, in_thread, loads
        self.labels = process.labels
        self.samples = process.samples  # timing.json's eval_envs: the evaluation process's arms
        self._turn = 0
        self._active: Any = None
        self._due = False

    @property
    def real_time_class(self) -> bool:
        return bool(self.process.real_time_class)

    def busy(self) -> bool:
        return self._active is not None

    def request(self, model: Any, step: int, episodes: int, seed: int) -> None:
        if self.busy():
            self._due = True
            return
        paths = (self.process,) if self.in_thread is None else (self.process, self.in_thread)
        self._active = paths[self._turn % len(paths)]
        self._turn += 1
        self._active.request(model, step, episodes, seed)

    def take(self, model: Any, step: int, episodes: int, seed: int) -> tuple[int, float, list[EvalResult]] | None:
        self.loads.append(os.getloadavg()[0])
        if self._active is None:
            return None
        done = self._active.take(model, step, episodes, seed)
        if done is None:
            return None
        self._active = None
        if self._due:
            self._due = False
            self.request(model, step, episodes, seed)
        return done  # type: ignore[no-any-return]

    def evaluate(self, model: Any, episodes: int, seed: int) -> list[EvalResult]:
        return self.process.evaluate(model, episodes, seed)  # type: ignore[no-any-return]

    def cancel(self) -> None:
        self._due = False
        if self._active is not None:
            self._active.cancel()
            self._active = None

    def close(self) -> None:
        try:
            self.process.close()
        finally:
            if self.in_thread is not None:
                self.in_thread.close()


@contextlib.contextmanager
def _both_paths(out: dict[str, Any], layout: str, thread: bool) -> Iterator[None]:
    """``train`` opens an ``_Alternating`` instead of its evaluation process alone (with the in-thread path beside it
    with ``thread``); it lands in ``out["paths"]``, the training envs (their ``ConcurrentVecEnv``) in
    ``out["training"]``. With ``layout`` "by-rank" both sets' loops tick at the phases of their ranks."""
    open_alongside = recipes.open_alongside
    build_concurrent_env = recipes.build_concurrent_env
    by_rank = layout == "by-rank"

    def kept(cfg: Any, **kwargs: Any) -> Any:
        if by_rank:
            kwargs["loop_phase_base"] = None
        venv, layout = build_concurrent_env(cfg, **kwargs)
        out["training"] = venv
        return venv, layout

    def both(
        specs: Sequence[tuple[str, str, dict[str, Any]]],
        *,
        real_time: bool,
        torch_threads: int = 1,
        rank: str,
        phase: float,
        task_id: bool = False,
    ) -> Any:
        assert not task_id, "the bench's envs have no env index"
        if by_rank:  # open_alongside's process, with the loops' phases left at their ranks
            process = Alongside(
                open_eval_process(
                    phased(specs, phase) if real_time else specs,
                    real_time=real_time,
                    torch_threads=torch_threads,
                    rt_rank_base=rank_bases(rank, len(specs))[1],
                    loop_phase_base=None,
                )
            )
        else:
            process = open_alongside(specs, real_time=real_time, torch_threads=torch_threads, rank=rank, phase=phase)
        in_thread = None
        try:
            if thread:
                in_thread = _InThread(phased(specs, phase) if real_time else specs, real_time)
        except BaseException:
            process.close()
            raise
        out["paths"] = _Alternating(process, in_thread, out.setdefault("loads", []))
        return out["paths"]

    recipes.open_alongside = both  # type: ignore[assignment]
    recipes.build_concurrent_env = kept
    try:
        yield
    finally:
        recipes.open_alongside = open_alongside
        recipes.build_concurrent_env = build_concurrent_env


@contextlib.contextmanager
def _collections(out: dict[str, Any]) -> Iterator[None]:
    """At the learner's start: one full collection frozen, one unfrozen (ms, and the objects each walked); then the
    pause (ms) of every generation-2 collection while it learns."""
    pauses: list[float] = out.setdefault("pauses_ms", [])
    started: list[float] = []
    learning = [False]
    learn = AsyncTD3.learn

    def timed_collect() -> tuple[float, int]:
        walked = len(gc.get_objects())
        t0 = time.perf_counter()
        gc.collect()
        return (time.perf_counter() - t0) * 1e3, walked

    def timed_learn(self: Any, *a: Any, **k: Any) -> Any:
        out["frozen_objects"] = gc.get_freeze_count()
        out["frozen_ms"], out["frozen_walked"] = timed_collect()
        gc.unfreeze()
        out["unfrozen_ms"], out["unfrozen_walked"] = timed_collect()
        gc.freeze()
        learning[0] = True
        try:
            return learn(self, *a, **k)
        finally:
            learning[0] = False

    def callback(phase: str, info: dict[str, Any]) -> None:
        if info.get("generation") != 2 or not learning[0]:
            return
        if phase == "start":
            started.append(time.perf_counter())
        elif started:
            pauses.append((time.perf_counter() - started.pop()) * 1e3)

    AsyncTD3.learn = timed_learn  # type: ignore[method-assign]
    gc.callbacks.append(callback)
    try:
        yield
    finally:
        gc.callbacks.remove(callback)
        AsyncTD3.learn = learn  # type: ignore[method-assign]


def _run(seconds: float, run_dir: Path, order: str, phase: float, layout: str, thread: bool) -> dict[str, Any]:
    heap: dict[str, Any] = {}
    both: dict[str, Any] = {}
    with _both_paths(both, layout, thread), _collections(heap):
        recipes.train(_config(run_dir, seconds, order, phase))
    paths = both["paths"]
    samples = {PROCESS: paths.process.samples, TRAINING: both["training"].samples}
    if paths.in_thread is not None:
        samples[THREAD] = paths.in_thread.venv.samples
    timing = json.loads((run_dir / "timing.json").read_text())
    return {
        "order": order,
        "phase": phase,
        "layout": layout,
        "samples": samples,
        "loads": both.get("loads", []),
        "real_time_class": paths.real_time_class,
        "heap": heap,
        "timing": timing,
    }


def _setting(order: str, phase: float, layout: str) -> str:
    return f"{order} ranked higher (evaluation phase {phase:g}; tick phases {layout})"


def _key(r: dict[str, Any]) -> tuple[str, float, str]:
    return r["order"], r["phase"], r["layout"]


def _rows(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per setting (order, phase and layout), evaluation arm and path (the setting's runs' samples pooled), and the
    training arms: the latency table's rows, the learner column naming the path and the setting."""
    rows = []
    for key in dict.fromkeys(_key(r) for r in results):
        runs = [r for r in results if _key(r) == key]
        for path in (PROCESS, THREAD, TRAINING):
            for label in runs[0]["samples"].get(path, {}):
                for metric in TIMING_METRICS:
                    pooled = [x for r in runs for x in r["samples"][path][label][metric]]
                    rows.append(_row(label, f"{path}, {_setting(*key)}", metric, summary(pooled)))
    return rows


def _row(label: str, learner: str, metric: str, s: dict[str, float]) -> dict[str, Any]:
    def num(key: str) -> float | None:
        v = s[key]
        return None if v != v else round(float(v), 3)  # NaN: no samples

    return {
        "env": label,
        "learner": learner,
        "metric": metric,
        "median_ms": num("p50"),
        "iqr_ms": num("iqr"),
        "p99_ms": num("p99"),
        "max_ms": num("max"),
        "count": int(s["count"]),
    }


def _print(results: list[dict[str, Any]], seconds: float) -> None:
    loads = [x for r in results for x in r["loads"]]
    load = f"load average (1 min) {min(loads):.1f}-{max(loads):.1f}" if loads else "load average unknown"
    print(
        f"\nhost {platform.node()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; four arms training and four"
        f" evaluated alongside on the wall clock, action cycle {CYCLE_S} s, {seconds:g} s per run, the runs alternating"
        f" their settings; {load}"
    )
    paths = "the evaluation process and a thread of the agent process" if THREAD in results[0]["samples"] else None
    where = f", evaluations alternating between {paths}" if paths else " (in the evaluation process)"
    print(f"\naction cycle (ms): the evaluation arms{where}, and the training arms")
    head = f"{'run':>3} {'env':<11} {'path':<28} {'median':>8} {'IQR':>7} {'p99':>8} {'n':>5}"
    for i, r in enumerate(results, 1):
        print(f"\nrun {i}: {_setting(*_key(r))}\n{head}\n" + "-" * len(head))
        for path in (PROCESS, THREAD, TRAINING):
            for label, metrics in r["samples"].get(path, {}).items():
                cyc = metrics["action_cycle"]
                if len(cyc) < 4:
                    print(f"{i:>3} {label:<11} {path:<28} {'(fewer than 4 cycles)':>30}")
                    continue
                s = summary(cyc)
                print(f"{i:>3} {label:<11} {path:<28} {s['p50']:>8.2f} {s['iqr']:>7.2f} {s['p99']:>8.2f} {len(cyc):>5}")
        print(f"    real-time class in the evaluation process: {r['real_time_class']}")
    print("\naction cycle (ms) per setting, its runs pooled: median / IQR of each evaluation-process and training arm")
    for row in _rows(results):
        if row["metric"] == "action_cycle" and not row["learner"].startswith(THREAD):
            print(f"  {row['env']:<11} {row['learner']:<76} {row['median_ms']} / {row['iqr_ms']}")
    print("\nthe agent process's heap when the learner starts: one full collection, frozen and unfrozen")
    for i, r in enumerate(results, 1):
        h = r["heap"]
        if "frozen_ms" not in h:
            continue
        print(
            f"{i:>3} frozen ({h['frozen_objects']:,} objects out of reach): {h['frozen_ms']:.1f} ms walking"
            f" {h['frozen_walked']:,}; unfrozen: {h['unfrozen_ms']:.1f} ms walking {h['unfrozen_walked']:,}"
        )
        pauses = h["pauses_ms"]
        if pauses:
            print(f"    full collections while learning: {len(pauses)}, longest {max(pauses):.1f} ms")
        else:
            print("    full collections while learning: none")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=150.0, help="wall time of each training run")
    parser.add_argument("--runs", type=int, default=1, help="runs per setting (the settings alternate)")
    parser.add_argument(
        "--phases",
        default="0,0.5",
        help="the evaluation arms' phases to compare (eval.alongside_phase, comma-separated; default: 0,0.5)",
    )
    parser.add_argument(
        "--orders",
        default=",".join(ORDERS),
        help=f"which set ranks higher (eval.alongside_rank, comma-separated; default: {','.join(ORDERS)})",
    )
    parser.add_argument(
        "--layouts",
        default=",".join(LAYOUTS),
        help=f"the loops' tick phases to compare (comma-separated; default: {','.join(LAYOUTS)})",
    )
    parser.add_argument(
        "--thread", action="store_true", help="alternate the evaluations with four arms evaluated on a thread"
    )
    parser.add_argument("--json", help="write the rows, the load and every run's records here")
    args = parser.parse_args()
    try:
        phases = [float(p) for p in args.phases.split(",")]
        for p in phases:
            phased([], p)
    except (ValueError, ConfigError) as exc:
        parser.error(f"--phases: expected numbers in [0, 1) separated by commas, got {args.phases!r} ({exc})")
    orders, layouts = args.orders.split(","), args.layouts.split(",")
    for name, given, known in (("--orders", orders, ORDERS), ("--layouts", layouts, LAYOUTS)):
        if not given or not set(given) <= set(known):
            parser.error(f"{name}: expected some of {', '.join(known)} separated by commas, got {','.join(given)!r}")
    settings = [(order, phase, layout) for phase in phases for order in orders for layout in layouts]
    results = []
    with tempfile.TemporaryDirectory(prefix="agent_rt_") as tmp:
        for k in range(1, len(settings) * args.runs + 1):
            order, phase, layout = settings[(k - 1) % len(settings)]
            results.append(_run(args.seconds, Path(tmp) / f"run_{k}", order, phase, layout, args.thread))
            if args.json:
                loads = [x for r in results for x in r["loads"]]
                out = {
                    "rows": _rows(results),
                    "load_average": [min(loads), statistics.median(loads), max(loads)] if loads else None,
                    "runs": results,
                }
                Path(args.json).write_text(json.dumps(out, indent=1))
    _print(results, args.seconds)


if __name__ == "__main__":
    main()
