"""``uniros bench timers``: fire-time error of bus timers at the two arms' hardware rates, side by side.

Runs a 10 Hz and a 25 Hz node timer concurrently for ``duration_s`` of wall time on the WallClock, then, in the
same run, the same two loops on plain ``asyncio.sleep`` to an absolute deadline (the peer: what a hand-written
asyncio loop gets), also for ``duration_s``. The phases run one after the other so neither disturbs the other.
Error = actual fire time - deadline.
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from collections.abc import Callable
from typing import Any

from uniros_async.bench.common import report
from uniros_async.bus import open_domain, open_node
from uniros_async.errors import ConfigError
from uniros_async.stats import summary

__all__ = ["TimerBenchConfig", "main"]


@dataclasses.dataclass(frozen=True, kw_only=True)
class TimerBenchConfig:
    duration_s: float = 60.0
    rates_hz: tuple[float, ...] = (10.0, 25.0)
    json_path: str | None = None
    progress: bool = True

    def __post_init__(self) -> None:
        if self.duration_s <= 0:
            raise ConfigError(f"duration_s must be > 0, got {self.duration_s}")
        if not self.rates_hz or any(r <= 0 for r in self.rates_hz):
            raise ConfigError(f"rates_hz must be positive, got {self.rates_hz}")


async def _asyncio_loop(period_s: float, duration_s: float, out: list[float]) -> None:
    loop = asyncio.get_running_loop()
    nxt = loop.time() + period_s
    end = loop.time() + duration_s
    while nxt < end:
        await asyncio.sleep(max(0.0, nxt - loop.time()))
        out.append((loop.time() - nxt) * 1e3)
        nxt += period_s


async def _wait(config: TimerBenchConfig, desc: str) -> None:
    t0 = time.monotonic()
    if not config.progress:
        await asyncio.sleep(config.duration_s)
        return
    from uniros_async._progress import progress_bar

    with progress_bar(total=round(config.duration_s), desc=desc, unit="s", leave=False) as bar:
        while (el := time.monotonic() - t0) < config.duration_s:
            await asyncio.sleep(min(1.0, config.duration_s - el))
            bar.n = round(min(time.monotonic() - t0, config.duration_s))
            bar.refresh()


async def _run(config: TimerBenchConfig, log: Callable[[str], None]) -> list[dict[str, Any]]:
    records: list[dict[str, Any]] = []
    peer: dict[float, list[float]] = {r: [] for r in config.rates_hz}
    async with open_domain("memory://") as domain, open_node("bench", domain=domain) as node:
        timers = {r: node.create_timer(1.0 / r, lambda: None) for r in config.rates_hz}
        await _wait(config, "uniros timers")
        for t in timers.values():
            t.cancel()
        async with asyncio.TaskGroup() as tg:
            for r in config.rates_hz:
                tg.create_task(_asyncio_loop(1.0 / r, config.duration_s, peer[r]))
            await _wait(config, "asyncio.sleep peer")
    for r in config.rates_hz:
        t = timers[r]
        err_ms = [(f - d) / 1e6 for f, d in zip(t.fire_times_ns, t.deadlines_ns, strict=True)]
        for impl, samples, overruns in (("uniros WallClock", err_ms, t.overruns), ("asyncio.sleep", peer[r], 0)):
            s = summary(samples)
            records.append(
                {
                    "impl": impl,
                    "rate_hz": r,
                    "median_ms": round(s["p50"], 4),
                    "p99_ms": round(s["p99"], 4),
                    "max_ms": round(s["max"], 4),
                    "count": s["count"],
                    "overruns": overruns,
                }
            )
    return records


def main(config: TimerBenchConfig, *, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Run, print the table, write JSON when asked."""
    records = asyncio.run(_run(config, log))
    head = (
        f"{'timer':<18} {'rate Hz':>7} {'median err ms':>14} {'p99 ms':>8} {'max ms':>8} {'fires':>6} {'overruns':>8}"
    )
    lines = [f"fire-time error over {config.duration_s:g} s (actual - deadline)", head, "-" * len(head)]
    for r in records:
        lines.append(
            f"{r['impl']:<18} {r['rate_hz']:>7g} {r['median_ms']:>14.4f} {r['p99_ms']:>8.3f} {r['max_ms']:>8.3f} "
            f"{r['count']:>6} {r['overruns']:>8}"
        )
    report("\n".join(lines), records, config.json_path, log)
    return records
