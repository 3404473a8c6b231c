"""The compiled shm ring end against the pure-Python one, in one run: what `_shm_ring_c.c` saves a vector step.

    python benchmarks/ab_shm_ring.py [ROUNDS]

Two `make_vec(["CartPole-v1"], pad=False)` (one worker each, over shm://) are made, one with the compiled
`RingEnd` on both ends (the default) and one with `UNIROS_SHM_PURE_PYTHON=1` (the worker inherits the choice), and
a bare `gymnasium.make("CartPole-v1")` beside them. Each round steps each of the three for a block of 500 steps,
in an order shuffled every round (seeded), after a 1 ms pause, as `uniros bench throughput` does. The env, the
code above the transport and the moment are the same for both vector envs, so the difference is the ring ends'.

Prints, per vector env, the median us per step, its overhead over the bare step (the median of the block medians'
differences, paired by round) with a 95 % interval (`uniros_async.stats.median_ci`), and the median per-round saving of
the compiled ring.
"""

from __future__ import annotations

import os
import random
import statistics
import sys
import time
from typing import Any

import gymnasium as gym
import numpy as np

from uniros_async.runtime import make_vec
from uniros_async.stats import median_ci
from uniros_async.transports._shm_ring import PURE_PYTHON_ENV, compiled_ring_end

STEPS = 500


def _vector_block(venv: Any, action: np.ndarray) -> float:
    t0 = time.perf_counter_ns()
    for _ in range(STEPS):
        venv.step(action)
    return (time.perf_counter_ns() - t0) / STEPS / 1000


def _bare_block(env: gym.Env[Any, Any]) -> float:
    t0 = time.perf_counter_ns()
    for _ in range(STEPS):
        _, _, terminated, truncated, _ = env.step(0)
        if terminated or truncated:
            env.reset()
    return (time.perf_counter_ns() - t0) / STEPS / 1000


def main(rounds: int) -> None:
    if compiled_ring_end() is None:
        sys.exit("the compiled RingEnd is not built here (pip install -e . with gcc): nothing to compare")
    venvs: dict[str, Any] = {}
    old = os.environ.pop(PURE_PYTHON_ENV, None)
    try:
        venvs["compiled"] = make_vec(["CartPole-v1"], pad=False)
        os.environ[PURE_PYTHON_ENV] = "1"
        venvs["python"] = make_vec(["CartPole-v1"], pad=False)
    finally:
        os.environ.pop(PURE_PYTHON_ENV, None)
        if old is not None:
            os.environ[PURE_PYTHON_ENV] = old
    try:
        for name, venv in venvs.items():
            venv.reset(seed=0)
            kind = type(venv._sup.workers[0].transport._ring).__module__
            print(f"{name}: RingEnd from {kind}")
        bare = gym.make("CartPole-v1")
        bare.reset(seed=0)
        action = np.zeros(1, dtype=np.int64)
        for venv in venvs.values():  # warm up
            _vector_block(venv, action)
        times: dict[str, list[float]] = {"compiled": [], "python": [], "bare": []}
        rng = random.Random(0)
        for _ in range(rounds):
            order = list(times)
            rng.shuffle(order)
            for name in order:
                time.sleep(0.001)
                times[name].append(_bare_block(bare) if name == "bare" else _vector_block(venvs[name], action))
        print(f"{rounds} rounds of {STEPS} steps each, blocks shuffled; us per step, medians")
        bare_us = statistics.median(times["bare"])
        print(f"  bare CartPole step        {bare_us:7.2f}")
        for name in ("compiled", "python"):
            over = [v - b for v, b in zip(times[name], times["bare"], strict=True)]
            lo, hi = median_ci(over)
            print(
                f"  make_vec, {name:9s} ring {statistics.median(times[name]):7.2f}   overhead "
                f"{statistics.median(over):6.2f}  (95 % CI {lo:.2f} .. {hi:.2f})"
            )
        saved = [p - c for p, c in zip(times["python"], times["compiled"], strict=True)]
        lo, hi = median_ci(saved)
        print(f"  the compiled ring saves   {statistics.median(saved):7.2f} us a step (95 % CI {lo:.2f} .. {hi:.2f})")
    finally:
        for venv in venvs.values():
            venv.close()


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 40)
