"""The agent process of `uniros train` in real time: the evaluation thread of `eval.alongside` in the real-time
class, and the heap frozen after set-up, each against its absence in the same run.

Four arms train (rx200 and ned2, sim and emulated real, on the wall clock, as configs/realtime_multitask_async.yaml
has them, at a shorter action cycle so that a run gathers enough cycles) with the asynchronous learner, and four more
are evaluated alongside, almost without a pause (short episodes, an evaluation every few vector steps). Three arms,
in turns, each `--rounds` times:

- `before`: the evaluation thread in the ordinary class and no frozen heap (`alongside.real_time_thread` and
  `recipes.freeze_heap` replaced by no-ops for that run: how `train` ran without them);
- `rt-eval`: the evaluation thread in the real-time class;
- `after`: both, as `train` runs now.

Printed per arm: the evaluation arms' action cycle (median and IQR over every evaluation, from timing.json; goal:
IQR < 1 ms), the training arms' action cycle, and the agent process's full (generation 2) collections while it
learned (count, median and longest pause), read with `gc.callbacks`.

    python benchmarks/agent_realtime.py            # 3 arms x 1 round x 45 s: about 3 minutes
    python benchmarks/agent_realtime.py --rounds 2 --seconds 40
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

from uniros_async.training import alongside as _alongside
from uniros_async.training import recipes as _recipes
from uniros_async.training.config import train_config_from_dict

alongside: Any = _alongside  # (patched per arm: see _arm)
recipes: Any = _recipes
ARMS = {"before": (False, False), "rt-eval": (True, False), "after": (True, True)}
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
def _arm(rt_eval: bool, freeze: bool) -> Iterator[None]:
    """For the run: without ``rt_eval`` the evaluation thread keeps the ordinary class, without ``freeze`` the heap
    is not frozen."""
    saved = alongside.real_time_thread, recipes.freeze_heap
    if not rt_eval:
        alongside.real_time_thread = lambda: contextlib.nullcontext(False)
    if not freeze:
        recipes.freeze_heap = lambda: None
    try:
        yield
    finally:
        alongside.real_time_thread, recipes.freeze_heap = saved


@contextlib.contextmanager
def _full_collections() -> Iterator[list[float]]:
    """The pause (ms) of every generation-2 collection while the learner learns (``AsyncTD3.learn``: after the
    set-up, whose own collection ``freeze_heap`` makes), in whichever thread triggered it."""
    from uniros_async.training.async_td3 import AsyncTD3

    out: list[float] = []
    started: list[float] = []
    learning = [False]
    learn = AsyncTD3.learn

    def timed_learn(self: Any, *a: Any, **k: Any) -> Any:
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
            out.append((time.perf_counter() - started.pop()) * 1e3)

    AsyncTD3.learn = timed_learn  # type: ignore[method-assign]
    gc.callbacks.append(callback)
    try:
        yield out
    finally:
        gc.callbacks.remove(callback)
        AsyncTD3.learn = learn  # type: ignore[method-assign]


def _run(arm: str, seconds: float, root: Path, k: int) -> dict[str, Any]:
    rt_eval, freeze = ARMS[arm]
    run_dir = root / f"{arm}_{k}"
    with _arm(rt_eval, freeze), _full_collections() as collections:
        recipes.train(_config(run_dir, seconds))
    timing = json.loads((run_dir / "timing.json").read_text())
    return {"arm": arm, "round": k, "timing": timing, "collections": collections}


def _cycle(stats: dict[str, Any]) -> str:
    c = stats["action_cycle"]
    n = int(c["count"] or 0)
    return f"{c['p50']:7.1f} {c['iqr']:6.2f} {n:5d}" if n else f"{'-':>7} {'-':>6} {0:5d}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=45.0, help="wall time of each training run")
    parser.add_argument("--rounds", type=int, default=1, help="runs of each arm, in turns")
    parser.add_argument("--json", help="write every run's timing.json and collection pauses here")
    args = parser.parse_args()
    results = []
    with tempfile.TemporaryDirectory(prefix="agent_rt_") as tmp:
        for k in range(1, args.rounds + 1):
            for arm in ARMS:
                results.append(_run(arm, args.seconds, Path(tmp), k))
                print(f"  {arm} round {k} done", flush=True)
                if args.json:
                    Path(args.json).write_text(json.dumps(results, indent=1))
    _print(results, args.seconds)


def _print(results: list[dict[str, Any]], seconds: float) -> None:
    print(
        f"\nhost {platform.node()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; four arms training and four"
        f" evaluated alongside on the wall clock, action cycle {CYCLE_S} s, {seconds:g} s per run"
    )
    head = f"{'arm':<8} {'rd':>2} {'env':<11} {'eval: med ms    IQR     n':>25}   {'train: med ms    IQR     n':>26}"
    print(head)
    print("-" * len(head))
    for r in results:
        t = r["timing"]
        for label, stats in t["eval_envs"].items():
            print(f"{r['arm']:<8} {r['round']:>2} {label:<11} {_cycle(stats):>25}   {_cycle(t['envs'][label]):>26}")
        print(f"{'':<12}evaluation thread real-time: {t['eval_real_time']}")
    print("\nfull (generation 2) collections in the agent process while it learned")
    print(f"{'arm':<8} {'rd':>2} {'count':>5} {'median ms':>9} {'max ms':>7}")
    for r in results:
        pauses = r["collections"]
        if pauses:
            med, top = statistics.median(pauses), max(pauses)
            print(f"{r['arm']:<8} {r['round']:>2} {len(pauses):>5} {med:>9.2f} {top:>7.2f}")
        else:
            print(f"{r['arm']:<8} {r['round']:>2} {0:>5}")
    iqrs: dict[str, list[float]] = {}
    for r in results:
        for stats in r["timing"]["eval_envs"].values():
            if stats["action_cycle"]["count"]:
                iqrs.setdefault(r["arm"], []).append(stats["action_cycle"]["iqr"])
    print("\nevaluation arms' action-cycle IQR, largest per arm (goal < 1 ms): ", end="")
    print(", ".join(f"{arm} {max(v):.2f} ms" for arm, v in iqrs.items()))


if __name__ == "__main__":
    main()
