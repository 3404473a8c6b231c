"""The agent process of `uniros train` in real time: the evaluation thread of `eval.alongside` in the real-time
class, and the heap frozen after set-up, each against its absence in the same run.

Four arms train (rx200 and ned2, sim and emulated real, on the wall clock, as configs/realtime_multitask_async.yaml
has them, at a shorter action cycle so that a run gathers enough cycles) with the asynchronous learner, and four more
are evaluated alongside, almost without a pause (short episodes, an evaluation every few vector steps).

- **Evaluation thread**: the evaluations alternate, one with the thread in the real-time class (as `train` runs
  it), the next without it (`alongside.real_time_thread` answered by a no-op for that evaluation: how `train` ran
  before), so both see the same moments of the host's load. Printed per evaluation arm and class: the action
  cycle's median and IQR over those evaluations (goal: IQR < 1 ms with the class).
- **Frozen heap**: when the learner starts (the set-up done, the heap frozen by `train`), one full collection is
  timed with the heap frozen and one with it unfrozen (then frozen again), back to back; and the full (generation
  2) collections while the learner learns are counted and timed (`gc.callbacks`).

    python benchmarks/agent_realtime.py                 # one 150 s run: about 3 minutes
    python benchmarks/agent_realtime.py --seconds 100 --runs 2
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import platform
import statistics
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from uniros_async.priority import real_time_thread
from uniros_async.training import alongside as _alongside
from uniros_async.training import recipes
from uniros_async.training.async_td3 import AsyncTD3
from uniros_async.training.config import train_config_from_dict

alongside: Any = _alongside  # its real_time_thread is answered per evaluation (_alternating)
CYCLE_S = 0.4
EPISODE_STEPS = 10


def _config(run_dir: Path, seconds: float) -> Any:
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
            "eval": {"every_steps": 16, "episodes": 1, "final_episodes": 1, "alongside": True},
            "checkpoint": {"every_steps": 0},
            "torch_threads": 1,
            "progress_bar": False,
        }
    )


@contextlib.contextmanager
def _alternating(cycles: dict[bool, dict[str, list[float]]]) -> Iterator[None]:
    """Evaluations alternate between the real-time class and none; each one's action cycles go to ``cycles[its
    class]`` per env label."""
    calls = [0]

    def every_other() -> Any:
        calls[0] += 1
        return real_time_thread() if calls[0] % 2 else contextlib.nullcontext(False)

    evaluate = alongside.Alongside.evaluate

    def recorded(self: Any, *a: Any, **k: Any) -> Any:
        had = {label: len(m["action_cycle"]) for label, m in self.venv.samples.items()}
        out = evaluate(self, *a, **k)
        for label, m in self.venv.samples.items():
            cycles[self.real_time_class].setdefault(label, []).extend(m["action_cycle"][had.get(label, 0) :])
        return out

    alongside.real_time_thread = every_other
    alongside.Alongside.evaluate = recorded
    try:
        yield
    finally:
        alongside.real_time_thread = real_time_thread
        alongside.Alongside.evaluate = evaluate


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


def _run(seconds: float, run_dir: Path) -> dict[str, Any]:
    cycles: dict[bool, dict[str, list[float]]] = {True: {}, False: {}}
    heap: dict[str, Any] = {}
    with _alternating(cycles), _collections(heap):
        recipes.train(_config(run_dir, seconds))
    timing = json.loads((run_dir / "timing.json").read_text())
    return {"cycles": {str(k): v for k, v in cycles.items()}, "heap": heap, "timing": timing}


def _iqr(samples: list[float]) -> float:
    q = statistics.quantiles(samples, n=4)
    return q[2] - q[0]


def _print(results: list[dict[str, Any]], seconds: float) -> None:
    print(
        f"\nhost {platform.node()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; four arms training and four"
        f" evaluated alongside on the wall clock, action cycle {CYCLE_S} s, {seconds:g} s per run"
    )
    print("\nevaluation arms' action cycle (ms), evaluations alternating between the real-time class and none")
    head = f"{'run':>3} {'env':<11} {'class':<9} {'median':>8} {'IQR':>7} {'p99':>8} {'n':>5}"
    print(head + "\n" + "-" * len(head))
    for i, r in enumerate(results, 1):
        for rt in ("False", "True"):
            for label, samples in sorted(r["cycles"][rt].items()):
                if len(samples) < 4:
                    continue
                p99 = statistics.quantiles(samples, n=100)[98]
                cls = "real-time" if rt == "True" else "ordinary"
                med, iqr = statistics.median(samples), _iqr(samples)
                print(f"{i:>3} {label:<11} {cls:<9} {med:>8.2f} {iqr:>7.2f} {p99:>8.2f} {len(samples):>5}")
    print("\nthe training arms' action cycle over the run (ms, timing.json): median / IQR")
    for i, r in enumerate(results, 1):
        envs = r["timing"]["envs"]
        print(
            f"{i:>3} "
            + ", ".join(f"{k} {v['action_cycle']['p50']:.1f} / {v['action_cycle']['iqr']:.2f}" for k, v in envs.items())
        )
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
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--json", help="write every run's records here")
    args = parser.parse_args()
    results = []
    with tempfile.TemporaryDirectory(prefix="agent_rt_") as tmp:
        for k in range(1, args.runs + 1):
            results.append(_run(args.seconds, Path(tmp) / f"run_{k}"))
            if args.json:
                Path(args.json).write_text(json.dumps(results, indent=1))
    _print(results, args.seconds)


if __name__ == "__main__":
    main()
