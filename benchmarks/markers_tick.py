"""The reach task's markers beside none, in one run: the env loop tick's own cost, the actuator cycle, and what one
publication of the markers costs the step.

    python benchmarks/markers_tick.py [--seconds 20]

One real-time ``uniros/Rx200Reach-v0`` env (10 Hz loop, 0.8 s action cycle, the sim arm in its process) runs
alternating windows of ``--window`` seconds with the markers published at their usual rate (``MARKER_PERIOD_S``),
at every step (the worst case), and not at all, so the three share the host's load. Each window records the wall
time of every ``_tick`` call (the loop's callback) and the time between two ticks.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import gymnasium as gym
import numpy as np

import uniros_async  # noqa: F401  (registers the envs)
from uniros_async.tasks.markers import MARKER_PERIOD_S
from uniros_async.tasks.reach import ReachEnv

MODES = {"usual": MARKER_PERIOD_S, "every step": 0.0, "none": float("inf")}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--seconds", type=float, default=60.0, help="total run time (default 60)")
    p.add_argument("--window", type=float, default=4.0, help="seconds per window (default 4)")
    args = p.parse_args()
    ticks: dict[str, list[float]] = {m: [] for m in MODES}
    cycles: dict[str, list[float]] = {m: [] for m in MODES}
    pubs: dict[str, list[float]] = {m: [] for m in MODES}
    starts: dict[str, list[float]] = {m: [] for m in MODES}
    mode = "none"
    tick, publish = ReachEnv._tick, ReachEnv._publish_markers

    def timed_tick(self: Any) -> None:
        t0 = time.perf_counter()
        tick(self)
        ticks[mode].append(time.perf_counter() - t0)
        starts[mode].append(t0)

    def timed_publish(self: Any) -> None:
        t0 = time.perf_counter()
        publish(self)
        pubs[mode].append(time.perf_counter() - t0)

    # the loop's timer binds _tick when it starts: wrapped on the class before the env is made
    ReachEnv._tick, ReachEnv._publish_markers = timed_tick, timed_publish  # type: ignore[method-assign]
    env = gym.make("uniros/Rx200Reach-v0")
    task: Any = env.unwrapped
    env.reset(seed=0)
    t_end = time.monotonic() + args.seconds
    order = list(MODES)
    i = 0
    while time.monotonic() < t_end:
        mode = order[i % len(order)]
        task._task_markers.period_s = MODES[mode]
        w_end = time.monotonic() + args.window
        while time.monotonic() < w_end:
            _, _, term, trunc, _ = env.step(env.action_space.sample() * 0.3)
            if term or trunc:
                env.reset()
        i += 1
    env.close()
    for m in MODES:  # the period between two ticks of one window (a gap across windows is left out)
        d = np.diff(np.array(starts[m])) * 1e3
        cycles[m] = d[d < 1.5 * 1e3 / task.env_loop_rate_hz].tolist()
    print(f"{'markers':<11} {'tick median us':>15} {'tick p99 us':>12} {'cycle median ms':>16} {'cycle IQR ms':>13} "
          f"{'publish median us':>18} {'publications':>13}")  # fmt: skip
    for m in MODES:
        tk, cy, pb = np.array(ticks[m]) * 1e6, np.array(cycles[m]), np.array(pubs[m]) * 1e6
        iqr = np.subtract(*np.percentile(cy, [75, 25])) if cy.size else float("nan")
        print(f"{m:<11} {np.median(tk):>15.1f} {np.percentile(tk, 99):>12.1f} {np.median(cy):>16.3f} {iqr:>13.3f} "
              f"{(np.median(pb) if pb.size else float('nan')):>18.1f} {pb.size:>13}")  # fmt: skip


if __name__ == "__main__":
    main()
