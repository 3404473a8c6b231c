"""What an rx200 step costs when several envs share one core.

Every case runs on one core (CPU affinity) and steps the throughput bench's env (accelerated rx200 reach, absolute
joint targets) with seeded random actions, each env attached to an event loop as a worker runs it
(``astep_through``), no requests or replies: the physics and the env's own work only. Printed per case, its CPU time
per env step (``time.process_time`` of each process):

- ``alone``: one process, one env;
- ``two processes``: two such processes at once, pinned to the same core, each stepping its own env flat out (the
  scheduler switches between them, as between two workers of a vector env that share a core);
- ``K envs, one process``: one process stepping K envs on its one loop, one after the other (``make_vec``'s
  ``envs_per_worker=K``).

The cases run in turns, ``--rounds`` times, so that each meets the same minutes of the host; the medians are printed.

    python benchmarks/shared_core_step_cost.py --rounds 5

Run it on a quiet host, not under ``nice``.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import subprocess
import sys
import time

import numpy as np


async def _step_envs(k: int, steps: int, cpu: int) -> float:
    """CPU seconds per env step of ``k`` envs stepped in turn on this loop, pinned to ``cpu``."""
    import gymnasium as gym

    import uniros_async  # noqa: F401  (registers the ids)
    from uniros_async.bench._vector_rows import ENV_ID, ENV_KW
    from uniros_async.envs.runtime import deferred_start
    from uniros_async.priority import freeze_heap
    from uniros_async.runtime.attached import areset_through, astep_through

    os.sched_setaffinity(0, {cpu})
    envs = []
    for _ in range(k):
        with deferred_start():
            env = gym.make(ENV_ID, **ENV_KW)
        await env.unwrapped.astart()  # type: ignore[attr-defined]
        envs.append(env)
    freeze_heap()
    envs[0].action_space.seed(0)
    actions = [envs[0].action_space.sample() for _ in range(steps + 20)]
    try:
        for env in envs:
            await areset_through(env, 0, None)
        for a in actions[:20]:  # warm-up
            for env in envs:
                await astep_through(env, a)
        c0 = time.process_time()
        for a in actions[20:]:
            for env in envs:
                await astep_through(env, a)
        return (time.process_time() - c0) / (steps * k)
    finally:
        for env in envs:
            await env.unwrapped.aclose()  # type: ignore[attr-defined]


def _spawn(k: int, steps: int, cpu: int) -> subprocess.Popen[str]:
    """This script as a child process stepping ``k`` envs on ``cpu`` (``--child``)."""
    return subprocess.Popen(
        [sys.executable, __file__, "--child", str(k), str(steps), str(cpu)], stdout=subprocess.PIPE, text=True
    )


def _case(processes: int, k: int, steps: int, cpu: int) -> float:
    """CPU ms per env step, the mean over ``processes`` processes started at once, each with ``k`` envs."""
    procs = [_spawn(k, steps, cpu) for _ in range(processes)]
    out = [float(p.communicate(timeout=600)[0].strip().splitlines()[-1]) for p in procs]
    if any(p.returncode for p in procs):
        raise SystemExit(f"a child failed: {[p.returncode for p in procs]}")
    return float(np.mean(out)) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=5, help="rounds of every case, in turns (default 5)")
    parser.add_argument("--steps", type=int, default=300, help="env steps per process and case (default 300)")
    parser.add_argument("--child", nargs=3, type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        k, steps, cpu = args.child
        print(asyncio.run(_step_envs(k, steps, cpu)))
        return
    cpu = max(os.sched_getaffinity(0))
    cases = {
        "alone": (1, 1),
        "two processes on one core": (2, 1),
        "2 envs, one process": (1, 2),
        "4 envs, one process": (1, 4),
    }
    results: dict[str, list[float]] = {name: [] for name in cases}
    for r in range(args.rounds):
        for name, (processes, k) in cases.items():
            results[name].append(_case(processes, k, args.steps // k, cpu))
        print(f"round {r + 1}: " + ", ".join(f"{n} {v[-1]:.3f}" for n, v in results.items()), flush=True)
    alone = float(np.median(results["alone"]))
    print(f"\nCPU ms per env step on core {cpu}, medians of {args.rounds} rounds (ratio to alone):")
    for name, values in results.items():
        med = float(np.median(values))
        print(f"  {name:<28} {med:6.3f} ms  ({med / alone:.3f}x)")


if __name__ == "__main__":
    main()
