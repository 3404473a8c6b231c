"""What a reset's goal costs the env loop's thread: the reach task drawing each goal at reset (``goal_pool=0``: IK
on the loop's thread) against picking it from the pool drawn at construction (``goal_pool=1024``, the default), in
the same run, resets alternating between the two envs.

Per arm and goal space, sim clock, in this process: the time of the reset hook (``_on_reset``, where the goal is
set; it runs on the loop's thread without yielding), the whole ``reset()`` as the caller sees it, and the
construction (which draws the pool)::

    python benchmarks/reset_goal_draw.py [RESETS]
"""

from __future__ import annotations

import platform
import sys
import time
from datetime import UTC, datetime
from typing import Any

import gymnasium as gym
import numpy as np

import uniros_async  # noqa: F401 - registers the envs


def _timed_hook(env: Any) -> list[float]:
    """Wrap ``env._on_reset`` on the instance; the list returned gets each call's time (ms)."""
    times: list[float] = []
    hook = env._on_reset

    def timed(q_arm: np.ndarray) -> None:
        t0 = time.perf_counter()
        hook(q_arm)
        times.append((time.perf_counter() - t0) * 1e3)

    env._on_reset = timed
    return times


def _row(name: str, ms: list[float]) -> str:
    a = np.asarray(ms)
    return f"{name:<22} median {np.median(a):7.3f}  p99 {np.percentile(a, 99):7.3f}  max {a.max():7.3f} ms"


def main(resets: int) -> None:
    print(
        f"host {platform.node()} {platform.processor() or platform.machine()}, {datetime.now(UTC):%Y-%m-%d %H:%M} UTC"
    )
    print(f"{resets} resets per env, alternating; sim clock")
    for env_id in ("uniros/Rx200Reach-v0", "uniros/Ned2Reach-v0"):
        for space in ("uniros-box", "workspace"):
            envs, built, hooks, calls = {}, {}, {}, {}
            for pool in (0, 1024):
                t0 = time.perf_counter()
                envs[pool] = gym.make(env_id, clock="sim", goal_space=space, goal_pool=pool)
                built[pool] = time.perf_counter() - t0
                hooks[pool] = _timed_hook(envs[pool].unwrapped)
                calls[pool] = []
            try:
                for i in range(resets):
                    for pool, env in envs.items():
                        t0 = time.perf_counter()
                        env.reset(seed=i)
                        calls[pool].append((time.perf_counter() - t0) * 1e3)
            finally:
                for env in envs.values():
                    env.close()
            print(f"\n{env_id} goal_space={space}")
            for pool, label in ((0, "drawn at reset"), (1024, "pool of 1024")):
                print(f"  {label}: construction {built[pool]:.2f} s")
                print("    " + _row("reset hook (loop)", hooks[pool]))
                print("    " + _row("reset() call", calls[pool]))


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 300)
