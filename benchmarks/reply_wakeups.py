"""What a vector step of crowded workers costs beside the physics.

A ``make_vec`` of N accelerated rx200 reach envs (the throughput bench's env and keywords) on this machine's cores,
stepped back to back after a warm-up; printed per N: steps/s as a % of the physics bound (min(N, cores) / the bare
env step, timed here first), the agent's voluntary and involuntary context switches per vector step (its wake-ups:
``/proc/<pid>/task/*/status``), the agent's and the workers' CPU time per env step, and the workers' context
switches per vector step (involuntary ones: a worker taken off its core in the middle of a step).

    python benchmarks/reply_wakeups.py --n-envs 4 8 --steps 300

Run it on a quiet host, not under ``nice`` (timing is what it measures).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from uniros_async.bench._stepmeter import cpu_s as _cpu_s
from uniros_async.bench._vector_rows import ENV_ID, ENV_KW, _actions
from uniros_async.bench.envs import make_env as _make_env


def _switches(pid: int) -> tuple[int, int]:
    """(voluntary, involuntary) context switches of every thread of ``pid`` so far."""
    vol = invol = 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{tid}/status") as f:
            for line in f:
                if line.startswith("voluntary_ctxt_switches"):
                    vol += int(line.split()[1])
                elif line.startswith("nonvoluntary_ctxt_switches"):
                    invol += int(line.split()[1])
    return vol, invol


def measure(n: int, steps: int, warmup: int = 20) -> str:
    """One line of figures for a vector env of ``n`` sub-envs stepped ``steps`` times."""
    from uniros_async.runtime import make_vec

    bare = _make_env(ENV_ID, ENV_KW)
    bare.reset(seed=0)
    actions = _actions(bare.action_space, steps + warmup + 200)
    times = []
    for a in actions[:200]:
        t0 = time.perf_counter()
        bare.step(a)
        times.append(time.perf_counter() - t0)
    bare_s = float(np.median(times))
    bare.close()
    venv = make_vec([ENV_ID] * n, pad=True, **ENV_KW)
    try:
        venv.reset(seed=0)
        batch = [np.stack([a] * n) for a in actions]
        for k in range(warmup):
            venv.step(batch[k])
        me, pids = os.getpid(), [p for p in venv.pids if p is not None]
        a0, w0 = _switches(me), [_switches(p) for p in pids]
        c0, wc0 = time.process_time(), [_cpu_s(p) or 0.0 for p in pids]
        step_t = []
        for k in range(warmup, warmup + steps):
            t0 = time.perf_counter()
            venv.step(batch[k])
            step_t.append(time.perf_counter() - t0)
        a1, w1 = _switches(me), [_switches(p) for p in pids]
        c1, wc1 = time.process_time(), [_cpu_s(p) or 0.0 for p in pids]
    finally:
        venv.close()
    sps = n / float(np.median(step_t))
    bound = min(n, os.cpu_count() or 1) / bare_s
    w_vol = sum(b[0] - a[0] for a, b in zip(w0, w1, strict=True)) / steps
    w_invol = sum(b[1] - a[1] for a, b in zip(w0, w1, strict=True)) / steps
    return (
        f"N={n}: {sps:.0f} steps/s = {100 * sps / bound:.1f} % of the bound (bare step {bare_s * 1e3:.2f} ms);"
        f" agent per vector step: {(a1[0] - a0[0]) / steps:.2f} voluntary, {(a1[1] - a0[1]) / steps:.2f}"
        f" involuntary switches; CPU per env step: agent {(c1 - c0) / (n * steps) * 1e3:.3f} ms, workers"
        f" {sum(b - a for a, b in zip(wc0, wc1, strict=True)) / (n * steps) * 1e3:.3f} ms; workers per vector step:"
        f" {w_vol:.2f} voluntary, {w_invol:.2f} involuntary switches"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-envs", type=int, nargs="+", default=[4, 8])
    parser.add_argument("--steps", type=int, default=300)
    args = parser.parse_args()
    for n in args.n_envs:
        print(measure(n, args.steps), flush=True)


if __name__ == "__main__":
    main()
