"""Two vector envs stepped in turn, step by step: `python benchmarks/in_turn_steps.py [shm|tcp] [BLOCKS]`.

Two `make_vec(["CartPole-v1"])` (a training env and an evaluation env, say), stepped 20 steps each in turn for
BLOCKS blocks (100 by default). Prints, for each env, the median time of the step at each of the 20 positions of a
block, then the median over the positions. The first steps of a block show what a worker that paused for the other
env's block costs (a wake-up, and where the scheduler placed it); `uniros bench throughput` gives one figure for
the same case in its third table.
"""

from __future__ import annotations

import statistics
import sys
import time

import numpy as np

from uniros_async.runtime import make_vec

BLOCK = 20


def main() -> None:
    transport = sys.argv[1] if len(sys.argv) > 1 else "shm"
    blocks = int(sys.argv[2]) if len(sys.argv) > 2 else 100
    envs = {name: make_vec(["CartPole-v1"], pad=False, transport=transport) for name in "AB"}
    try:
        for venv in envs.values():
            venv.reset(seed=0)
        at: dict[str, list[list[int]]] = {name: [[] for _ in range(BLOCK)] for name in envs}
        for b in range(blocks):
            for name in "AB" if b % 2 else "BA":
                step = envs[name].step
                for k in range(BLOCK):
                    action = np.array([k % 2])
                    t0 = time.perf_counter_ns()
                    step(action)
                    at[name][k].append(time.perf_counter_ns() - t0)
        for name, positions in at.items():
            medians = [statistics.median(p) / 1e3 for p in positions]
            print(f"{transport} env {name}: {' '.join(f'{m:.0f}' for m in medians)} us")
            print(f"{transport} env {name}: median over the positions {statistics.median(medians):.1f} us")
    finally:
        for venv in envs.values():
            venv.close()


if __name__ == "__main__":
    main()
