"""``uniros bench throughput``: vectorised stepping over worker processes, ours against gymnasium and SB3.

In one run, for N = 1, 2, 4, 8 copies of the rx200 reach env in accelerated turn-based mode (``turn_based=True``:
the sim advances in lockstep inside ``step``, as fast as the CPU allows), each implementation steps random
actions: ``uniros_async.make_vec`` (workers over shared memory), gymnasium's ``AsyncVectorEnv`` and SB3's
``SubprocVecEnv`` (both over pickled pipes, spawn). Reported: aggregate env steps per second, and the
per-step overhead = time per vector step minus the bare env's step time measured in this process in the
same run (meaningful at N = 1; above that the workers share 2 cores).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from uniros_async.bench.stats import report
from uniros_async.errors import ConfigError

__all__ = ["IMPLS", "ThroughputBenchConfig", "main"]

IMPLS = ("uniros", "gymnasium-async", "sb3-subproc")
ENV_ID = "uniros/Rx200Reach-v0"
ENV_KW: dict[str, Any] = {"turn_based": True, "max_episode_steps": 10**9}


@dataclasses.dataclass(frozen=True, kw_only=True)
class ThroughputBenchConfig:
    n_envs: tuple[int, ...] = (1, 2, 4, 8)
    steps: int = 100
    quick: bool = False
    json_path: str | None = None

    def __post_init__(self) -> None:
        if not self.n_envs or min(self.n_envs) < 1 or self.steps < 5:
            raise ConfigError(f"n_envs must be >= 1 and steps >= 5, got {self.n_envs}, {self.steps}")


def _make_env() -> Any:
    import gymnasium as gym

    import uniros_async  # noqa: F401

    return gym.make(ENV_ID, **ENV_KW)


def _bare_step_s(steps: int) -> float:
    env = _make_env()
    try:
        env.reset(seed=0)
        times = []
        for _ in range(steps):
            a = env.action_space.sample()
            t0 = time.perf_counter()
            env.step(a)
            times.append(time.perf_counter() - t0)
    finally:
        env.close()
    return float(np.median(times))


def _vector(impl: str, n: int) -> tuple[Any, Callable[[], Any], Callable[[Any], Any]]:
    """(vec env, reset(), step(actions)) for one implementation."""
    if impl == "uniros":
        from uniros_async import make_vec

        venv = make_vec([ENV_ID] * n, **ENV_KW)
        return venv, lambda: venv.reset(seed=0), venv.step
    if impl == "gymnasium-async":
        from gymnasium.vector import AsyncVectorEnv

        venv = AsyncVectorEnv([_make_env] * n, context="spawn")
        return venv, lambda: venv.reset(seed=0), venv.step
    from stable_baselines3.common.vec_env import SubprocVecEnv

    sb = SubprocVecEnv([_make_env] * n, start_method="spawn")
    return sb, sb.reset, lambda a: (sb.step_async(a), sb.step_wait())


def _run(impl: str, n: int, steps: int, bare_s: float) -> dict[str, Any]:
    venv, reset, step = _vector(impl, n)
    try:
        reset()
        space = venv.action_space
        rng = np.random.default_rng(0)
        shape = (n, *space.shape[-1:])
        lo, hi = np.broadcast_to(space.low, shape), np.broadcast_to(space.high, shape)
        step(rng.uniform(lo, hi).astype(np.float32))  # warm-up
        per_step = []
        for _ in range(steps):
            a = rng.uniform(lo, hi).astype(np.float32)
            t0 = time.perf_counter()
            step(a)
            per_step.append(time.perf_counter() - t0)
    finally:
        venv.close()
    med = float(np.median(per_step))
    return {
        "impl": impl,
        "n_envs": n,
        "steps_per_s": round(n / med, 1),
        "overhead_us": round((med - bare_s) * 1e6, 1),
    }


def main(config: ThroughputBenchConfig, *, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    ns = tuple(n for n in config.n_envs if n <= 4) if config.quick else config.n_envs
    steps = min(config.steps, 30) if config.quick else config.steps
    bare_s = _bare_step_s(steps)
    records = []
    for n in ns:
        for impl in IMPLS:
            records.append(_run(impl, n, steps, bare_s))
    head = f"{'N':>3} {'impl':<16} {'env steps/s':>12} {'overhead us/step':>17}"
    lines = [f"bare {ENV_ID} step (turn-based, accelerated): {bare_s * 1e3:.2f} ms median", head, "-" * len(head)]
    for r in records:
        lines.append(f"{r['n_envs']:>3} {r['impl']:<16} {r['steps_per_s']:>12.1f} {r['overhead_us']:>17.1f}")
    for n in ns:
        rows = {r["impl"]: r for r in records if r["n_envs"] == n}
        ratio = rows["uniros"]["steps_per_s"] / rows["gymnasium-async"]["steps_per_s"]
        lines.append(f"N={n}: uniros / gymnasium-async steps/s = {ratio:.2f}x")
    report("\n".join(lines), records, config.json_path, log)
    return records
