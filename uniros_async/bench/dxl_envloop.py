"""``python -m uniros_async.bench.dxl_envloop``: the real-time env loop of the rx200 on its (virtual) Dynamixel bus.

For each rate (default 10 Hz, the paper's, and 100 Hz): a ``uniros robot vbus rx200`` process (in the real-time
class above every loop, as the servos answer whatever the host runs), and in this process the rx200 reach env with
``robot="dxl://PTY?profile_ms=0"`` and ``env_loop_rate_hz`` at the rate (the bus loop follows the env loop's rate,
raised to two ticks per Bus Watchdog window), on the wall clock, driven for ``duration_s`` by the scripted reach
agent of ``uniros bench envloop``. The heap is frozen before the env starts, and once it has started the threads it
started are put in the loops' real-time class, as a worker process does for its env.

Reports the env loop's actuator cycle, action cycle, observation age and action latency (``looptiming``) against
the main job's goals (actuator median within 0.1 ms of the period, IQR < 0.5 ms), with the host's load average
before and after each row. A RobotError of the arm (a bus silent past the servos' watchdog) ends its row, which is
reported with the error.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

from uniros_async.bench.common import report
from uniros_async.bench.dxl import _vbus
from uniros_async.bench.looptiming import ScriptedReachAgent, Series, format_table, to_records
from uniros_async.errors import ConfigError, RobotError
from uniros_async.stats import loop_metrics

__all__ = ["DxlEnvLoopConfig", "main"]


@dataclasses.dataclass(frozen=True, kw_only=True)
class DxlEnvLoopConfig:
    rates_hz: tuple[float, ...] = (10.0, 100.0)
    duration_s: float = 60.0
    action_cycle_s: float = 0.8
    think_ms: float = 0.0
    margin_ms: float = 10.0
    """The bus client's host-side slack per transaction (the ``dxl://`` URI's ``margin_ms``)."""
    seed: int = 0
    json_path: str | None = None

    def __post_init__(self) -> None:
        if not self.rates_hz or any(r <= 0 for r in self.rates_hz):
            raise ConfigError(f"rates_hz: expected rates > 0, got {self.rates_hz}")
        if self.duration_s <= 0 or self.think_ms < 0 or self.margin_ms <= 0:
            raise ConfigError("duration_s and margin_ms must be > 0, think_ms >= 0")
        if self.think_ms / 1e3 >= self.action_cycle_s:
            raise ConfigError(f"think_ms={self.think_ms} must be below the action cycle ({self.action_cycle_s} s)")


def _load() -> str:
    one, five, _ = os.getloadavg()
    return f"{one:.1f}/{five:.1f}"


def _row(rate_hz: float, cfg: DxlEnvLoopConfig, log: Callable[[str], None]) -> tuple[Series, str]:
    import gymnasium as gym

    import uniros_async  # noqa: F401  (registers the envs)
    from uniros_async.priority import freeze_heap, raise_loop_priority, thread_ids

    agent = ScriptedReachAgent("rx200", think_ms=cfg.think_ms, seed=cfg.seed)
    load_before = _load()
    with _vbus("rx200", None, rt=False) as path:  # the vbus takes the servos' real-time class itself
        # frozen before the env starts: a full collection once the bus runs would hold its loop past the watchdog
        freeze_heap()
        before = thread_ids()
        env = gym.make(
            "uniros/Rx200Reach-v0",
            robot=f"dxl://{path}?profile_ms=0&margin_ms={cfg.margin_ms:g}",
            clock="wall",
            env_loop_rate_hz=rate_hz,
            action_cycle_s=cfg.action_cycle_s,
            action_mode="absolute",
            max_episode_steps=10**9,
        )
        error = ""
        try:
            env.reset(seed=cfg.seed)
            for tid in thread_ids() - before:
                raise_loop_priority(thread_id=tid)
            u: Any = env.unwrapped
            u.timing.clear()  # after the reset, which aligned the step deadlines to the loop's ticks
            reset_after: set[int] = set()
            recv_ns: list[int] = []
            end = time.monotonic() + cfg.duration_s
            try:
                while time.monotonic() < end:
                    _, _, terminated, _, _ = env.step(agent.act())
                    recv_ns.append(time.monotonic_ns())
                    if terminated:
                        reset_after.add(len(recv_ns) - 1)
                        env.reset()
            except RobotError as exc:
                error = str(exc)
                log(f"{rate_hz:g} Hz: {error}")
            snap = u.timing_snapshot()
            n = len(recv_ns)
            snap = {k: (v[:n] if k in ("action_ns", "step_ns") else v) for k, v in snap.items()}
            series = Series(
                env=f"rx200 dxl {rate_hz:g} Hz",
                learner="scripted",
                samples=loop_metrics(snap, reset_after=reset_after, recv_ns=recv_ns),
                period_ms=1e3 / rate_hz,
                action_cycle_ms=cfg.action_cycle_s * 1e3 if cfg.think_ms == 0 else None,
                step_overruns=int(snap["step_overruns"]),
            )
        finally:
            env.close()
            gc.unfreeze()
    note = f"{rate_hz:g} Hz: load average (1/5 min) {load_before} before, {_load()} after"
    if error:
        note += f"; ended early: {error}"
    return series, note


def main(config: DxlEnvLoopConfig, *, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Run each rate's row, print the table (and the JSON records when asked). Returns the records."""
    series: list[Series] = []
    notes: list[str] = []
    for rate in config.rates_hz:
        s, note = _row(rate, config, log)
        series.append(s)
        notes.append(note)
    records = to_records("dxl-envloop", series)
    head = (
        f"rx200 on uniros robot vbus (pty), host {os.uname().nodename} ({os.cpu_count()} cores), "
        f"{time.strftime('%Y-%m-%d %H:%M %Z')}, {config.duration_s:g} s a row"
    )
    report("\n".join([head, format_table(series, records), *notes]), records, config.json_path, log)
    return records


def _parse(argv: Sequence[str] | None) -> DxlEnvLoopConfig:
    p = argparse.ArgumentParser(prog="python -m uniros_async.bench.dxl_envloop", description=__doc__.split("\n")[0])
    p.add_argument("--rates", type=float, nargs="+", default=[10.0, 100.0], help="env loop rates in Hz")
    p.add_argument("--duration", type=float, default=60.0, help="wall seconds per rate (default 60)")
    p.add_argument("--margin-ms", type=float, default=10.0, help="the bus client's slack per transaction")
    p.add_argument("--json", dest="json_path", default=None, metavar="PATH", help="also write the records here")
    a = p.parse_args(argv)
    return DxlEnvLoopConfig(
        rates_hz=tuple(a.rates), duration_s=a.duration, margin_ms=a.margin_ms, json_path=a.json_path
    )


if __name__ == "__main__":
    main(_parse(None))
