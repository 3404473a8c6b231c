"""How ``uniros bench throughput`` times a row: the bare env's own step time (``Floor``, ``bare_block``), the
back-to-back phase of a vector env (``tight``, ``timed_block``) with the CPU its processes and the host's cores
spent meanwhile (``Meter``), and the 95 % interval of a row's steps/s (``sps_ci``)."""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from uniros_async.bench.common import cpu_times
from uniros_async.stats import median_ci

__all__ = [
    "BOUND_BLOCK",
    "CI_GOAL",
    "MAX_TIGHT_STEPS",
    "MIN_TIGHT_STEPS",
    "TIGHT_CHUNK",
    "TRAIL_S",
    "Floor",
    "Meter",
    "bare_block",
    "cpu_s",
    "quiesce",
    "sps_ci",
    "sps_halfwidth",
    "tight",
    "timed_block",
]

CI_GOAL = 0.025
"""The half-width, relative to the figure, that a row at ``CROWDED_N`` or more sub-envs steps until its steps/s
interval is within."""
MIN_TIGHT_STEPS = 400
"""The fewest steps the back-to-back phase of such a row takes (or ``--steps`` if more): rows of 3 chunks (147
steps) scattered from run to run by more than their intervals said (91-98 % of the bound where rows of 9 chunks
gave 97-101 % in the same hour, on the 2-core host of docs/performance.md)."""
MAX_TIGHT_STEPS = 2000
"""The most steps the back-to-back phase of such a row takes (~40 s at N = 8 on 2 cores)."""
TIGHT_CHUNK = 50
"""Steps between two looks at the interval."""
TRAIL_S = 0.005
"""Untimed pause after each vector block of the alternating phase: a worker replies before the servo tick that its
step's last sim event also woke (~1 ms of physics), which would otherwise run during the bare step timed next."""
BOUND_BLOCK = 16
"""Steps of the bare env timed after each chunk of a crowded row's back-to-back phase (the first left out)."""


class Floor:
    """The env's own step time, nothing else: the same env attached to an event loop that this thread runs, each
    step's coroutine (``astep_through``: the same wrappers) timed from inside the loop, so neither a thread
    hand-over nor the loop's start and stop nor the servo tick that trails the step is counted."""

    def __init__(self, env_id: str, kwargs: dict[str, Any]) -> None:
        import gymnasium as gym

        from uniros_async.envs.runtime import deferred_start

        self.loop = asyncio.new_event_loop()
        with deferred_start():
            self.env: Any = gym.make(env_id, **kwargs)
        base: Any = self.env.unwrapped
        self.loop.run_until_complete(base.astart())

    def reset(self, seed: int) -> None:
        from uniros_async.runtime.attached import areset_through

        self.loop.run_until_complete(areset_through(self.env, seed, None))

    def step_s(self, action: Any) -> float:
        from uniros_async.runtime.attached import astep_through

        async def timed() -> float:
            t0 = time.perf_counter()
            await astep_through(self.env, action)
            return time.perf_counter() - t0

        return self.loop.run_until_complete(timed())

    def close(self) -> None:
        base: Any = self.env.unwrapped
        self.loop.run_until_complete(base.aclose())
        self.loop.close()


def bare_block(bare: Any, actions: list[Any], ks: range) -> list[float]:
    """Steps ``ks`` of the bare env back to back, each timed (an episode's end resets it, untimed: the trivial env's
    episodes end; the vector envs reset themselves)."""
    times: list[float] = []
    for k in ks:
        t0 = time.perf_counter()
        _, _, terminated, truncated, _ = bare.step(actions[k])
        times.append(time.perf_counter() - t0)
        if terminated or truncated:
            bare.reset()
    return times


def quiesce(env: Any) -> None:
    """Let the bare env's loop thread finish what its last step's sim event woke (the next tick's physics), so that
    it does not run, holding the GIL, during the vector env's step that is timed next."""
    rt = getattr(env.unwrapped, "_rt", None)
    if rt is not None:
        rt.call(asyncio.sleep(0), 5.0)


def cpu_s(pid: int | None) -> float | None:
    """CPU time of process ``pid`` so far, all its threads (the scheduler's nanosecond count in
    ``/proc/<pid>/task/*/schedstat``); None where that cannot be read."""
    if pid is None:
        return None
    total = 0
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{tid}/schedstat") as f:
                total += int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return None
    return total / 1e9


def sps_ci(per_step: list[float], n: int) -> tuple[float, float]:
    """The 95 % interval of a row's steps/s (``n`` / the median time per vector step): ``median_ci`` of the step
    times, inverted."""
    lo, hi = median_ci(per_step)
    return n / hi, n / lo


def sps_halfwidth(per_step: list[float], n: int) -> float:
    """The larger side of ``sps_ci`` relative to the steps/s figure (inf while too few steps for an interval)."""
    lo, hi = sps_ci(per_step, n)
    if np.isnan(lo):
        return float("inf")
    sps = n / float(np.median(per_step))
    return max(hi - sps, sps - lo) / sps


class Meter:
    """CPU time of a row's local worker processes and of this process, and what the host's cores did, summed over
    the stretches of the back-to-back phase in which the vector env steps (``start`` / ``stop``): figures that do not
    depend on how busy the host is."""

    def __init__(self, pids: list[int | None]) -> None:
        self.pids = pids
        self.steps = 0
        self.workers_s = 0.0
        self.agent_s = 0.0
        self.wall_s = 0.0
        self.ticks: list[int] | None = [0] * 8
        self.readable = bool(pids)
        self._start: tuple[list[float | None], float, list[int] | None, float] | None = None

    def start(self) -> None:
        if self.readable:
            self._start = [cpu_s(p) for p in self.pids], time.process_time(), cpu_times(), time.perf_counter()

    def stop(self, steps: int) -> None:
        """The end of a stretch of ``steps`` vector steps (the workers' CPU is read after their trailing work)."""
        if self._start is None:
            return
        workers0, agent0, host0, t0 = self._start
        self._start = None
        host1, wall_s, agent1 = cpu_times(), time.perf_counter() - t0, time.process_time()
        time.sleep(TRAIL_S)  # the step's trailing servo tick is the workers' too
        workers1 = [cpu_s(p) for p in self.pids]
        spent = [b - a for a, b in zip(workers0, workers1, strict=True) if a is not None and b is not None]
        if len(spent) != len(self.pids):
            self.readable = False
            return
        self.workers_s += sum(spent)
        self.agent_s += agent1 - agent0
        self.wall_s += wall_s
        self.steps += steps
        if host0 is None or host1 is None or self.ticks is None:
            self.ticks = None
        else:
            self.ticks = [t + b - a for t, a, b in zip(self.ticks, host0, host1, strict=True)]

    def fill(self, record: dict[str, Any], n: int) -> None:
        """Add the CPU time per env step of the workers and of the agent, and the cores' shares, to ``record``."""
        if not self.readable or not self.steps:
            return
        record["worker_cpu_ms"] = round(self.workers_s / (n * self.steps) * 1e3, 3)
        record["agent_cpu_ms"] = round(self.agent_s / (n * self.steps) * 1e3, 3)
        if self.ticks is not None:  # what the cores did meanwhile: our processes, idle, others
            cores = os.cpu_count() or 1
            record["cores_ours_pct"] = round(100 * (self.workers_s + self.agent_s) / (self.wall_s * cores), 1)
            record["cores_idle_pct"] = round(100 * (self.ticks[3] + self.ticks[4]) / max(sum(self.ticks), 1), 1)


def tight(
    step: Callable[[Any], Any],
    batch: list[Any],
    actions: list[Any],
    k0: int,
    steps: int,
    n: int,
    meter: Meter,
    bare: Any = None,
) -> tuple[list[float], list[float]]:
    """The back-to-back phase of a row from step ``k0``: its vector step times, and the bare step times of the
    bound. Without ``bare``: ``steps`` steps in one stretch. With ``bare`` (a row of ``throughput.CROWDED_N`` or
    more sub-envs): chunks of ``TIGHT_CHUNK`` steps until there are ``steps`` (``MIN_TIGHT_STEPS`` if more) and the
    steps/s interval is within ``CI_GOAL`` (at most ``MAX_TIGHT_STEPS`` in all, or as many as ``batch`` holds from
    ``k0``), each followed by ``BOUND_BLOCK`` steps of the bare env with the chunk's first actions: the bound is
    timed in the same seconds as the rate it bounds (this host's speed drifts within a second). The first step of
    each chunk and block, which starts on idle cores, is left out; the bare env steps on from where its last block
    left it."""
    if bare is None:
        meter.start()
        block = timed_block(step, batch, range(k0, k0 + steps))
        meter.stop(steps)
        return block, []
    times: list[float] = []
    bare_t: list[float] = []
    last = min(len(batch), k0 + max(MAX_TIGHT_STEPS, steps))
    least = max(steps, min(MIN_TIGHT_STEPS, MAX_TIGHT_STEPS))
    k = k0
    while k < last and (len(times) < least or sps_halfwidth(times, n) > CI_GOAL):
        ks = range(k, min(k + TIGHT_CHUNK, last))
        meter.start()
        times += timed_block(step, batch, ks)[1:]
        meter.stop(len(ks))  # (and waits for the workers' trailing work, which must not overlap the bare block)
        bare_t += bare_block(bare, actions, range(k, min(k + BOUND_BLOCK, len(actions))))[1:]
        quiesce(bare)
        k += TIGHT_CHUNK
    return times, bare_t


def timed_block(step: Callable[[Any], Any], batch: list[Any], ks: range) -> list[float]:
    """Steps ``ks`` of a vector env back to back, each timed."""
    times: list[float] = []
    for k in ks:
        t0 = time.perf_counter()
        step(batch[k])
        times.append(time.perf_counter() - t0)
    return times
