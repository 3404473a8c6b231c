"""``uniros bench envloop``: the real-time env loop's timing, per arm, in one run.

Runs the rx200 (10 Hz) and ned2 (25 Hz) reach envs for ``duration_s`` of wall time each (one after the other,
or ``--concurrent`` together in this process), with an agent that aims at random reachable points and thinks
for a random 0 to ``think_ms`` before each step. Reports, as the paper's Figures 8 to 10 do, the actuator cycle (time
between env-loop ticks that sent a command), the action cycle (time between agent steps), the observation age
(how old the returns were when the agent got them) and the action latency (from the agent's action reaching the
loop to the first command sent with it), as ``looptiming`` defines them: median, IQR, p99, max and count. The envs
run in this process (a thread each), so this shows the env loop alone; ``uniros bench latency`` runs them in
worker processes beside learners.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable
from typing import Any

from uniros_async.bench.common import report
from uniros_async.bench.looptiming import ScriptedReachAgent, Series, format_table, loop_metrics, to_records
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


def _run_one(arm: str, cfg: EnvLoopBenchConfig, out: dict[str, Series], bar: Any) -> None:
    import gymnasium as gym

    import uniros_async  # noqa: F401

    agent = ScriptedReachAgent(arm, think_ms=cfg.think_ms, seed=cfg.seed)
    env = gym.make(  # absolute targets: the scripted agent's actions are joint targets
        ENVS[arm], robot=cfg.robot, action_cycle_s=cfg.action_cycle_s, action_mode="absolute", max_episode_steps=10**9
    )
    try:
        env.reset(seed=cfg.seed)
        u: Any = env.unwrapped  # a ReachEnv
        u.timing.clear()  # after the reset, which aligned the step deadlines to the loop's ticks
        reset_after: set[int] = set()
        recv_ns: list[int] = []
        end = time.monotonic() + cfg.duration_s
        while time.monotonic() < end:
            # every action is the joint target of a random reachable point, so every tick sends a command and the
            # actuator cycle is the loop's own
            _, _, terminated, _, _ = env.step(agent.act())
            recv_ns.append(time.monotonic_ns())
            if bar is not None:
                bar.update(cfg.action_cycle_s)
            if terminated:
                reset_after.add(len(recv_ns) - 1)
                env.reset()
        snap = u.timing_snapshot()
        out[arm] = Series(
            env=f"{arm} {cfg.robot}",
            learner="scripted",
            samples=loop_metrics(snap, reset_after=reset_after, recv_ns=recv_ns),
            period_ms=1e3 / u.env_loop_rate_hz,
            # the action cycle is the period between actions reaching the loop: an agent that thinks a random
            # 0-think_ms before each step spreads it by that much, so its goal applies only to an agent that does not
            action_cycle_ms=cfg.action_cycle_s * 1e3 if cfg.think_ms == 0 else None,
            step_overruns=int(snap["step_overruns"]),
        )
    finally:
        env.close()


def main(config: EnvLoopBenchConfig, *, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Run, print the table, write JSON when asked. Returns records like the latency benchmark's."""
    results: dict[str, Series] = {}
    bar = None
    if config.progress:
        from uniros_async._progress import progress_bar

        total = config.duration_s * (1 if config.concurrent else len(config.arms))
        bar = progress_bar(
            total=round(total),
            desc="env loop bench",
            unit="s",
            leave=False,
            bar_format="{l_bar}{bar}| {n:.0f}/{total_fmt} s",
        )
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
    series = [results[arm] for arm in config.arms]
    records = to_records("envloop-concurrent" if config.concurrent else "envloop", series)
    table = format_table(series, records)
    if config.think_ms > 0:
        table += (
            f"\naction cycle: spread by the agent's random 0-{config.think_ms:g} ms of thinking before each step (no "
            "goal shown; --think-ms 0 for an agent that acts at once, or `uniros bench latency` for real learners)"
        )
    report(table, records, config.json_path, log)
    return records
