"""What validating env keyword arguments costs: this tree against another checkout of uniros_async, in one run.

    python benchmarks/ab_config_construction.py OTHER_TREE [ROUNDS]

OTHER_TREE is a checkout to compare with (e.g. ``git archive <commit> | tar -x -C /tmp/base``). Each round runs
one child process per tree, in an order shuffled every round (seeded); each child measures, with the same
keyword arguments (``clock="sim"``, ``reward_type="sparse"``, ``action_cycle_s=0.1``, ``unsafe_action="hold"``):

- ``import``: the time to import ``uniros_async.tasks.reach`` after ``uniros_async`` and gymnasium (the envs, the
  robots, MuJoCo, pinocchio and, where the configs are pydantic models, pydantic), in ms, once per child;
- ``kwargs``: the median time of ``split_kwargs(ReachEnv, kwargs)`` (the env keyword arguments split and
  validated, what every env construction and every ``make`` / ``make_vec`` spec check runs), in us;
- ``make``: the median time of ``gym.make("uniros/Rx200Reach-v0", **kwargs)`` and ``close()`` over 5 envs
  (after one warm-up), in ms;
- ``step``: the median ``env.step`` time over 100 steps of one env (sim clock, 0.1 s action cycles), in us, to
  show that the step path does not touch validation.

Prints each tree's medians over the rounds.
"""

from __future__ import annotations

import json
import os
import random
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

KWARGS: dict[str, Any] = {"clock": "sim", "reward_type": "sparse", "action_cycle_s": 0.1, "unsafe_action": "hold"}
ENV_ID = "uniros/Rx200Reach-v0"


def _child() -> None:
    import gymnasium as gym
    import numpy as np

    import uniros_async  # noqa: F401

    t0 = time.perf_counter_ns()
    from uniros_async.tasks.reach import ReachEnv  # what a worker imports to build the env (with pydantic, here)

    import_ms = (time.perf_counter_ns() - t0) / 1e6
    from uniros_async.envs.task import split_kwargs

    samples = []
    for _ in range(20):
        t0 = time.perf_counter_ns()
        for _ in range(100):
            split_kwargs(ReachEnv, KWARGS)
        samples.append((time.perf_counter_ns() - t0) / 100 / 1000)
    kwargs_us = statistics.median(samples)
    makes = []
    for i in range(6):
        t0 = time.perf_counter_ns()
        env = gym.make(ENV_ID, **KWARGS)
        env.close()
        if i:
            makes.append((time.perf_counter_ns() - t0) / 1e6)
    env = gym.make(ENV_ID, **KWARGS)
    env.reset(seed=0)
    action = np.zeros(env.action_space.shape, dtype=np.float32)
    steps = []
    for _ in range(100):
        t0 = time.perf_counter_ns()
        env.step(action)
        steps.append((time.perf_counter_ns() - t0) / 1000)
    env.close()
    make_ms, step_us = statistics.median(makes), statistics.median(steps)
    print(json.dumps({"import": import_ms, "kwargs": kwargs_us, "make": make_ms, "step": step_us}))


def main(other: Path, rounds: int) -> None:
    here = Path(__file__).resolve().parents[1]
    trees = {"this": here, "other": other.resolve()}
    rng = random.Random(0)
    results: dict[str, list[dict[str, float]]] = {name: [] for name in trees}
    for _ in range(rounds):
        order = list(trees)
        rng.shuffle(order)
        for name in order:
            env = {**os.environ, "PYTHONPATH": str(trees[name])}
            out = subprocess.run(
                [sys.executable, __file__, "--child"],
                env=env,
                cwd=trees[name],
                capture_output=True,
                text=True,
                check=True,
            )
            results[name].append(json.loads(out.stdout.strip().splitlines()[-1]))
    for name, tree in trees.items():
        r = results[name]
        print(
            f"{name:5s} {tree}: import {statistics.median(x['import'] for x in r):6.1f} ms   "
            f"kwargs {statistics.median(x['kwargs'] for x in r):5.1f} us   "
            f"make+close {statistics.median(x['make'] for x in r):6.1f} ms   "
            f"step {statistics.median(x['step'] for x in r):7.1f} us   ({rounds} rounds)"
        )


if __name__ == "__main__":
    if sys.argv[1:] == ["--child"]:
        _child()
    else:
        main(Path(sys.argv[1]), int(sys.argv[2]) if len(sys.argv) > 2 else 5)
