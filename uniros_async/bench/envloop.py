"""``uniros bench envloop``: the real-time env loop's timing, per arm, in one run.

Runs the rx200 (10 Hz) and ned2 (25 Hz) reach envs for ``duration_s`` of wall time each (one after the other,
or ``--concurrent`` together in this process), with an agent that aims at random reachable points and thinks
for a random 0 to ``think_ms`` before each step. Reports, as the paper's Figures 8 to 10 do, the actuator cycle (time
between env-loop ticks that sent a command), the action cycle (time between agent steps), the observation age
(how old the returns were when the agent got them) and the action latency (from the agent's action reaching the
loop to the first command sent with it): median, IQR, p99, max and count. The full latency benchmark (learners,
several workers, turn-based baseline) builds on this.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from uniros_async.bench.stats import report, summary
from uniros_async.errors import ConfigError

__all__ = ["EnvLoopBenchConfig", "main"]

ENVS = {"rx200": "uniros/Rx200Reach-v0", "ned2": "uniros/Ned2Reach-v0"}


@dataclasses.dataclass(frozen=True, kw_only=True)
class EnvLoopBenchConfig:
    duration_s: float = 60.0
    arms: tuple[str, ...] = ("rx200", "ned2")
    action_cycle_s: float = 0.8
    think_ms: float = 50.0
    robot: str = "sim"
    concurrent: bool = False
    seed: int = 0
    json_path: str | None = None
    progress: bool = True

    def __post_init__(self) -> None:
        bad = [a for a in self.arms if a not in ENVS]
        if bad:
            raise ConfigError(f"unknown arm(s) {bad}; choose from {sorted(ENVS)}")
        if self.duration_s <= 0 or self.think_ms < 0:
            raise ConfigError("duration_s must be > 0 and think_ms >= 0")
        if self.think_ms / 1e3 >= self.action_cycle_s:
            raise ConfigError(f"think_ms={self.think_ms} must be below the action cycle ({self.action_cycle_s} s)")


def _run_one(arm: str, cfg: EnvLoopBenchConfig, out: dict[str, Any], bar: Any) -> None:
    import gymnasium as gym

    import uniros_async  # noqa: F401

    rng = np.random.default_rng(cfg.seed)
    env = gym.make(ENVS[arm], robot=cfg.robot, action_cycle_s=cfg.action_cycle_s, max_episode_steps=10**9)
    try:
        env.reset(seed=cfg.seed)
        u: Any = env.unwrapped  # a ReachEnv
        u.timing.clear()
        end = time.monotonic() + cfg.duration_s
        while time.monotonic() < end:
            # the agent thinks (for a random time) and picks a safe action: the joint target of a random
            # reachable point, so every tick sends a command and the actuator cycle is the loop's own
            t_think = time.monotonic() + rng.uniform(0, cfg.think_ms / 1e3)
            q = u.kin.ik(u.sample_goal(rng), rng=rng)[0]
            action = (2 * (q - u._lower) / (u._upper - u._lower) - 1).clip(-1, 1).astype(np.float32)
            time.sleep(max(0.0, t_think - time.monotonic()))
            _, _, terminated, _, _ = env.step(action)
            if bar is not None:
                bar.update(cfg.action_cycle_s)
            if terminated:
                env.reset()
        t = u.timing
        out[arm] = {
            "actuator_cycle": t.periods_ms(t.command_ns),
            "action_cycle": t.periods_ms(t.step_ns),
            "observation_age": [x / 1e6 for x in t.observation_age_ns],
            "action_latency": [x / 1e6 for x in t.action_latency_ns],
            "period_ms": 1e3 / u.env_loop_rate_hz,
        }
    finally:
        env.close()


def main(config: EnvLoopBenchConfig, *, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Run, print the table, write JSON when asked. Returns records like the latency benchmark's."""
    results: dict[str, Any] = {}
    bar = None
    if config.progress:
        from tqdm import tqdm

        total = config.duration_s * (1 if config.concurrent else len(config.arms))
        bar = tqdm(total=round(total), desc="env loop bench", unit="s", leave=False, bar_format="{l_bar}{bar}| {n:.0f}/{total_fmt} s")
    if config.concurrent:
        threads = [threading.Thread(target=_run_one, args=(a, config, results, None)) for a in config.arms]
        for th in threads:
            th.start()
        t0 = time.monotonic()
        while any(th.is_alive() for th in threads):
            time.sleep(0.5)
            if bar is not None:
                bar.n = min(config.duration_s, time.monotonic() - t0)
                bar.refresh()
        for th in threads:
            th.join()
    else:
        for arm in config.arms:
            _run_one(arm, config, results, bar)
    if bar is not None:
        bar.close()
    records = []
    for arm in config.arms:
        r = results[arm]
        for metric in ("actuator_cycle", "action_cycle", "observation_age", "action_latency"):
            s = summary(r[metric])
            records.append(
                {
                    "scenario": "envloop-concurrent" if config.concurrent else "envloop",
                    "env": f"{arm} {config.robot}",
                    "learner": "random",
                    "metric": metric,
                    "median_ms": round(s["p50"], 4),
                    "iqr_ms": round(s["iqr"], 4),
                    "p99_ms": round(s["p99"], 4),
                    "max_ms": round(s["max"], 4),
                    "count": s["count"],
                }
            )
    head = f"{'env':<14} {'metric':<16} {'median ms':>10} {'IQR ms':>8} {'p99 ms':>8} {'max ms':>8} {'count':>6}  target"
    lines = [head, "-" * len(head)]
    for rec in records:
        arm = str(rec["env"]).split()[0]
        target = {"actuator_cycle": f"{results[arm]['period_ms']:g} +- 0.1", "action_cycle": f"{config.action_cycle_s * 1e3:g} +- 0.5"}.get(str(rec["metric"]), "")
        lines.append(
            f"{rec['env']:<14} {rec['metric']:<16} {rec['median_ms']:>10.3f} {rec['iqr_ms']:>8.3f} {rec['p99_ms']:>8.3f} "
            f"{rec['max_ms']:>8.3f} {rec['count']:>6}  {target}"
        )
    report("\n".join(lines), records, config.json_path, log)
    return records
