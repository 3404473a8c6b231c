"""``python -m uniros_async.bench.dxl_zeroshot``: a committed policy, zero-shot and in real time, on the rx200 on its
virtual Dynamixel bus with the emulated real arm's perturbations.

A ``uniros robot vbus rx200 --emulate-real`` process (in the real-time class above every loop, as the servos answer
whatever the host runs) and, in this process, the reach env with ``robot="dxl://PTY?profile_ms=0&..."`` on the wall
clock, driven by the weights-only policy (``training.weights.load_policy``: NumPy, no torch). Once the env has
started the heap is frozen (before each start of the env, as a full collection once the bus runs would hold its
loop past the servos' watchdog); with ``rank`` the threads it started go into the loops'
real-time class at that rank and this thread into the actors' (``priority.real_time_thread``).

Episode ``k`` resets with seed ``seed * 100_000 + k``, so every episode's goal is fixed whatever happened before
it. An episode that a ``RobotError`` ends (the arm's bus silent past the servos' watchdog, or servos that did not
answer within the bus's retries: a stalled host) counts as failed and is reported as aborted; the env is then
built again (a new start-up on the same bus) and the run goes on. The result: successes of ``episodes``, the 95 %
Wilson interval, mean return and length, the aborted episodes and their errors, the host's load average; ``--json``
writes it.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import gc
import json
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from uniros_async.bench.dxl import _vbus
from uniros_async.errors import ConfigError, UnirosError

__all__ = ["ZeroShotConfig", "main"]

DENSE_POLICY = "docs/results/checkpoints/rx200_reach_dense_td3_uniros"


@dataclasses.dataclass(frozen=True, kw_only=True)
class ZeroShotConfig:
    policy: str = DENSE_POLICY
    episodes: int = 200
    seed: int = 0
    emulation_seed: int = 0
    query: str = "profile_ms=0&margin_ms=100&rate=50"
    """The ``dxl://`` query after the pty's path (``placement.parse_dxl_uri``)."""
    rank: int | None = None
    """The env loop's real-time rank (``priority.raise_loop_priority``), and this thread in the actors' class; None:
    both stay in the ordinary class. On a pty the bytes between its two ends are moved by a kernel worker of the
    ordinary class, which real-time threads that keep the cores busy hold up."""
    json_path: str | None = None

    def __post_init__(self) -> None:
        if self.episodes < 1:
            raise ConfigError(f"episodes must be >= 1, got {self.episodes}")


def _make_env(path: str, cfg: ZeroShotConfig) -> tuple[Any, set[int]]:
    import gymnasium as gym

    import uniros_async  # noqa: F401  (registers the envs)
    from uniros_async.priority import thread_ids

    before = thread_ids()
    env = gym.make(
        "uniros/Rx200Reach-v0",
        reward_type="dense",
        action_mode="delta",
        robot=f"dxl://{path}?{cfg.query}",
        clock="wall",
    )
    return env, before


def main(config: ZeroShotConfig, *, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Run the episodes; returns the result (also written to ``json_path``)."""
    from uniros_async.priority import freeze_heap, raise_loop_priority, real_time_thread, thread_ids
    from uniros_async.training.sweep import wilson
    from uniros_async.training.weights import load_policy

    policy = load_policy(config.policy)
    load_before = os.getloadavg()
    successes, returns, lengths = 0, [], []
    aborted: list[dict[str, Any]] = []
    t_start = time.monotonic()
    extra = ["--emulate-real", "--seed", str(config.emulation_seed)]
    actor = real_time_thread() if config.rank is not None else contextlib.nullcontext(False)
    with _vbus("rx200", None, rt=False, extra=extra) as path, actor as rt:  # the vbus takes the servos' class itself
        env: Any = None
        try:
            for ep in range(config.episodes):
                if env is None:
                    # frozen before the env starts: a full collection once the bus runs would hold its loop past
                    # the servos' watchdog
                    freeze_heap()
                    env, before = _make_env(path, config)
                ret, length, ok = 0.0, 0, False
                try:
                    obs, _ = env.reset(seed=config.seed * 100_000 + ep)
                    if before:
                        if config.rank is not None:
                            for tid in thread_ids() - before:
                                raise_loop_priority(config.rank, thread_id=tid)
                        before = set()
                    done = False
                    while not done:
                        obs, reward, terminated, truncated, info = env.step(policy(obs))
                        ret += float(reward)
                        length += 1
                        done = bool(terminated or truncated)
                    ok = bool(info.get("is_success", False))
                except UnirosError as exc:  # a RobotError, or a step that met the env's loop ending for one
                    aborted.append({"episode": ep, "steps": length, "error": str(exc)})
                    log(f"episode {ep}: aborted after {length} steps: {exc}")
                    env.close()
                    env = None
                    gc.unfreeze()
                successes += ok
                returns.append(ret)
                lengths.append(length)
                log(
                    f"episode {ep + 1}/{config.episodes}: {'success' if ok else 'failure'} in {length} steps; "
                    f"{successes}/{ep + 1} ({100.0 * successes / (ep + 1):.1f} %), {len(aborted)} aborted, "
                    f"{time.monotonic() - t_start:.0f} s"
                )
        finally:
            if env is not None:
                env.close()
            gc.unfreeze()
    low, high = wilson(successes, config.episodes)
    result: dict[str, Any] = {
        "policy": config.policy,
        "env": "uniros/Rx200Reach-v0 (dense, delta)",
        "robot": f"dxl://PTY?{config.query}",
        "bus": f"uniros robot vbus rx200 --emulate-real --seed {config.emulation_seed}",
        "episodes": config.episodes,
        "successes": successes,
        "success_rate": successes / config.episodes,
        "wilson95": [round(low, 4), round(high, 4)],
        "mean_return": round(float(np.mean(returns)), 3),
        "std_return": round(float(np.std(returns)), 3),
        "mean_length": round(float(np.mean(lengths)), 2),
        "aborted": aborted,
        "seed": config.seed,
        "real_time": rt,
        "wall_s": round(time.monotonic() - t_start, 1),
        "load_average_before": [round(x, 2) for x in load_before],
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
        "host": f"{os.uname().nodename} ({os.cpu_count()} cores)",
        "date": time.strftime("%Y-%m-%d %H:%M %Z"),
    }
    log(
        f"{successes}/{config.episodes} = {100.0 * result['success_rate']:.1f} % (95 % Wilson {100 * low:.1f}-"
        f"{100 * high:.1f} %), mean return {result['mean_return']}, mean length {result['mean_length']}, "
        f"{len(aborted)} aborted, {result['wall_s']} s"
    )
    if config.json_path:
        Path(config.json_path).write_text(json.dumps(result, indent=2) + "\n")
        log(f"wrote {config.json_path}")
    return result


def _parse(argv: Sequence[str] | None) -> ZeroShotConfig:
    p = argparse.ArgumentParser(prog="python -m uniros_async.bench.dxl_zeroshot", description=__doc__.split("\n")[0])
    p.add_argument("--policy", default=DENSE_POLICY, help="a weights directory (default: the committed dense one)")
    p.add_argument("--episodes", type=int, default=200)
    p.add_argument("--seed", type=int, default=0, help="episode k resets with seed SEED * 100000 + k")
    p.add_argument("--emulation-seed", type=int, default=0, help="the emulated arm's seed (vbus --seed)")
    p.add_argument("--query", default=ZeroShotConfig.query, help="the dxl:// query (default %(default)s)")
    p.add_argument("--rank", type=int, default=None, help="the env loop's real-time rank (default: ordinary class)")
    p.add_argument("--json", dest="json_path", default=None, metavar="PATH")
    a = p.parse_args(argv)
    return ZeroShotConfig(
        policy=a.policy,
        episodes=a.episodes,
        seed=a.seed,
        emulation_seed=a.emulation_seed,
        query=a.query,
        rank=a.rank,
        json_path=a.json_path,
    )


if __name__ == "__main__":
    main(_parse(None))
