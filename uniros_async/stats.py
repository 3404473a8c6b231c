"""Order statistics of samples (medians, percentiles and their confidence, never means of latencies), and the
timing metrics of real-time env loops computed from an env's timing records. The benchmarks, training's timing
logs and the tests share them.

From an env's timing records (``Timing.snapshot()``, fetched from a worker with ``call("timing_snapshot")``) and
what the agent saw (when each step's returns reached it, which steps ended an episode), ``loop_metrics`` gives
four series, in ms:

- **actuator cycle**: the period between consecutive env-loop ticks that both sent a command. A period that
  spans a tick which sent nothing (before the first command, while a simulated arm is teleported home, while an
  unsafe action is held) is no actuator cycle and is left out; so are hold commands sent outside a tick.
- **action cycle**: the period between the agent's actions reaching the env loop (``action_ns``). ``step``
  returns on an absolute deadline, so the agent's compute time (inference, a synchronous learner's updates, a
  vector env waiting for its slowest member) shows here and not in the step returns. Periods spanning a reset
  (an episode boundary; in a vector env, any member's) are left out, and so is the period of the first step
  after each reset: that step ends on the first point of the action-cycle grid far enough away
  (``RobotEnv._step_deadline``: 1/8 to 9/8 of a cycle on a wall clock, 1/2 to 3/2 on a sim clock), so its length
  says nothing about the agent (every recording here starts with a reset).
- **observation age**: how old the returns were when the agent got them: the time the agent received them
  minus the tick that built them, both on the machine's monotonic clock (wall-clock envs; the agent's receive
  time is recorded by the benchmark). In a vector env this includes the wait for the member whose step returns
  last. Steps at a reset are left out, as for the action cycle. Without agent-side times (or for sim-clock envs,
  whose world is paused between ``step`` returning and the agent receiving) it is the age when ``step``
  returned, in the env's clock.
- **action latency**: from an action reaching the loop to the first command sent with it (env-side).
"""

from __future__ import annotations

import collections.abc
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["ENV_SIDE_AGE", "METRICS", "loop_metrics", "median_ci", "since", "summary"]

METRICS = ("actuator_cycle", "action_cycle", "observation_age", "action_latency")
"""The four env-loop metrics ``loop_metrics`` computes, in ms."""
ENV_SIDE_AGE = "observation_age_at_step_return"
"""``loop_metrics``'s extra series: the observation age when ``step`` returned, in the env."""


def summary(samples: Sequence[float]) -> dict[str, float]:
    """p50, p90, p99, IQR, min, max and count of ``samples`` (NaN when empty)."""
    if len(samples) == 0:
        nan = float("nan")
        return {"p50": nan, "p90": nan, "p99": nan, "iqr": nan, "min": nan, "max": nan, "count": 0}
    a = np.asarray(samples, dtype=np.float64)
    p25, p50, p75, p90, p99 = np.percentile(a, [25, 50, 75, 90, 99])
    return {
        "p50": float(p50),
        "p90": float(p90),
        "p99": float(p99),
        "iqr": float(p75 - p25),
        "min": float(a.min()),
        "max": float(a.max()),
        "count": int(a.size),
    }


def median_ci(samples: Sequence[float] | np.ndarray, level: float = 0.95) -> tuple[float, float]:
    """A distribution-free confidence interval of the median of ``samples``: the order statistics of ranks ``l`` and
    ``n + 1 - l``, ``l`` the largest rank with P(Binomial(n, 1/2) < l) <= (1 - level) / 2, so the interval holds the
    true median with probability >= ``level``. It assumes independent samples; steps timed back to back share the
    moment's load, so read it as the least the figure is uncertain by. (NaN, NaN) when ``samples`` are too few for
    any such pair of ranks (fewer than 6 at 95 %).
    """
    n = len(samples)
    tail = (1.0 - level) / 2
    total = 2**n
    rank = 0  # l
    term = 1  # comb(n, rank), updated in place: exact integers, one multiplication a rank
    outcomes = 0  # of the 2**n, how many have at most ``rank`` successes: P(X < rank + 1) * 2**n
    while rank < n // 2:
        outcomes += term
        if outcomes / total > tail:
            break
        term = term * (n - rank) // (rank + 1)
        rank += 1
    if rank == 0:
        return float("nan"), float("nan")
    a = np.sort(np.asarray(samples, dtype=np.float64))
    return float(a[rank - 1]), float(a[n - rank])


def _as_int_list(x: Any) -> list[int]:
    return [int(v) for v in x]


def since(snapshot: collections.abc.Mapping[str, Any], earlier: collections.abc.Mapping[str, Any]) -> dict[str, Any]:
    """What ``snapshot`` recorded after ``earlier`` (an older snapshot of the same env): every series without the
    entries ``earlier`` had, ``step_overruns`` as a difference.

    Benchmarks take a snapshot instead of clearing the timing just before a learner's ``learn`` (which resets the
    env itself): a reset aligns its step deadlines to the newest env-loop tick, and a cleared history has none.
    """
    out: dict[str, Any] = {}
    for key, value in snapshot.items():
        before = earlier.get(key)
        if isinstance(value, list):
            out[key] = value[len(before) if isinstance(before, list) else 0 :]
        else:
            out[key] = int(value) - int(before or 0)
    return out


def loop_metrics(
    snapshot: collections.abc.Mapping[str, Any],
    *,
    reset_after: collections.abc.Collection[int] = (),
    recv_ns: collections.abc.Sequence[int] | None = None,
) -> dict[str, list[float]]:
    """The four metrics (module docstring) of one env, in ms.

    Args:
        snapshot: the env's ``Timing.snapshot()`` since just before the first step (cleared after a reset, or cut
            with ``since``), so that ``action_ns[k]`` and ``step_ns[k]`` belong to step k.
        reset_after: indices of the steps after which a reset happened (the period from step k's action to step
            k + 1's is then not an action cycle, nor is the aligned first step's, k + 1 to k + 2). The snapshot
            must start with the first step after a reset (its period, 0 to 1, is left out too).
        recv_ns: ``time.monotonic_ns()`` when the agent received step k's returns, for wall-clock envs; None:
            use the env-side age.

    Returns:
        ``{"actuator_cycle": [...], "action_cycle": [...], "observation_age": [...], "action_latency": [...]}``,
        and ``ENV_SIDE_AGE``: the age when ``step`` returned in the env (before the trip to the agent and, in a
        vector env, the wait for its other envs), for the table's footnote.
    """
    ticks = _as_int_list(snapshot.get("tick_ns", []))
    commanded = set(_as_int_list(snapshot.get("command_ns", [])))
    actuator = [(b - a) / 1e6 for a, b in zip(ticks, ticks[1:], strict=False) if a in commanded and b in commanded]
    actions = _as_int_list(snapshot.get("action_ns", []))
    skip = set(reset_after)
    # the recording starts after a reset: step 0, and the step after each later reset, ends on the aligned grid
    first_steps = {0} | {k + 1 for k in skip}
    action_cycle = [
        (actions[k + 1] - actions[k]) / 1e6 for k in range(len(actions) - 1) if k not in skip and k not in first_steps
    ]
    steps = _as_int_list(snapshot.get("step_ns", []))
    env_age = _as_int_list(snapshot.get("observation_age_ns", []))
    if recv_ns is not None and len(steps) == len(env_age) and len(recv_ns) >= len(steps):
        # the tick that built step k's returns was at step_ns[k] - age[k]; the agent got them at recv_ns[k]
        # (a step after which an env reset is left out: that env's returns were replaced by the reset's, and in a
        # vector env the others' waited for the reset)
        age = [(recv_ns[k] - (steps[k] - env_age[k])) / 1e6 for k in range(len(steps)) if k not in skip]
    else:
        age = [a / 1e6 for a in env_age]
    latency = [a / 1e6 for a in _as_int_list(snapshot.get("action_latency_ns", []))]
    return {
        "actuator_cycle": actuator,
        "action_cycle": action_cycle,
        "observation_age": age,
        "action_latency": latency,
        ENV_SIDE_AGE: [a / 1e6 for a in env_age],
    }
