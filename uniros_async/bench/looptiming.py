"""Timing of real-time env loops as the paper's Figures 8 to 10 show it; shared by ``uniros bench envloop`` and
``uniros bench latency``.

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

``ScriptedReachAgent`` is the timing-only agent: it aims at random reachable points (so every tick sends a
command) and thinks for a random time before each step.
"""

from __future__ import annotations

import collections.abc
import dataclasses
import textwrap
import time
from typing import Any

import numpy as np

from uniros_async.bench.stats import summary

__all__ = ["METRICS", "ScriptedReachAgent", "Series", "format_table", "loop_metrics", "since", "to_records"]

METRICS = ("actuator_cycle", "action_cycle", "observation_age", "action_latency")
ENV_SIDE_AGE = "observation_age_at_step_return"
ARM_OF_ENV_ID = {"uniros/Rx200Reach-v0": "rx200", "uniros/Ned2Reach-v0": "ned2"}

LEGEND = """\
actuator cycle: period between consecutive env-loop ticks that sent a command
action cycle: period between the agent's actions reaching the env loop (a learner's compute shows here; step
  returns on an absolute deadline); periods spanning a reset (episode boundary), and the first step's after it
  (which ends on the action-cycle grid: 1/8 to 9/8 of a cycle later), are left out
observation age: how old the returns were when the agent received them (in a vector env: when the member whose
  step returns last returned; steps at a reset left out)
action latency: from an action reaching the env loop to the first command sent with it (unsafe actions, never sent,
  have none)"""


@dataclasses.dataclass(kw_only=True)
class Series:
    """One env's (or one env and learner's) samples of every metric, in ms, and what to compare them with.

    ``row`` and ``box`` place the samples in the plot: one row of panels per ``row``, one box per ``box``.
    """

    env: str
    learner: str
    samples: dict[str, list[float]]
    period_ms: float | None = None
    action_cycle_ms: float | None = None
    row: str = ""
    box: str = ""
    step_overruns: int = 0

    def __post_init__(self) -> None:
        self.row = self.row or self.env
        self.box = self.box or self.learner


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


def to_records(scenario: str, series: collections.abc.Iterable[Series]) -> list[dict[str, Any]]:
    """JSON records ``{"scenario", "env", "learner", "metric", "median_ms", "iqr_ms", "p99_ms", "max_ms",
    "count"}``, one per series and metric (NaN figures, for a metric without samples, become None)."""

    def num(x: float) -> float | None:
        return None if not np.isfinite(x) else round(x, 4)

    out: list[dict[str, Any]] = []
    for s in series:
        for metric in METRICS:
            st = summary(s.samples.get(metric, []))
            out.append(
                {
                    "scenario": scenario,
                    "env": s.env,
                    "learner": s.learner,
                    "metric": metric,
                    "median_ms": num(st["p50"]),
                    "iqr_ms": num(st["iqr"]),
                    "p99_ms": num(st["p99"]),
                    "max_ms": num(st["max"]),
                    "count": int(st["count"]),
                }
            )
    return out


def _target(s: Series, metric: str) -> str:
    if metric == "actuator_cycle" and s.period_ms is not None:
        return f"{s.period_ms:g} +- 0.1, IQR < 0.5"
    if metric == "action_cycle" and s.action_cycle_ms is not None:
        return f"{s.action_cycle_ms:g} +- 0.5, IQR < 1"
    return ""


def format_table(series: collections.abc.Sequence[Series], records: collections.abc.Sequence[dict[str, Any]]) -> str:
    """The terminal table of ``records`` (as ``to_records(..., series)`` made them), with goals and a legend."""
    targets = {(s.env, s.learner, m): _target(s, m) for s in series for m in METRICS}
    w_env = max([len("env"), *(len(str(r["env"])) for r in records)])
    w_learner = max([len("learner"), *(len(str(r["learner"])) for r in records)])
    head = (
        f"{'env':<{w_env}} {'learner':<{w_learner}} {'metric':<16} {'median ms':>10} {'IQR ms':>8} {'p99 ms':>9} "
        f"{'max ms':>9} {'count':>6}  goal"
    )
    lines = [head, "-" * len(head)]

    def f(x: Any, width: int, digits: int = 3) -> str:
        return f"{'-':>{width}}" if x is None else f"{x:>{width}.{digits}f}"

    for r in records:
        lines.append(
            f"{r['env']:<{w_env}} {r['learner']:<{w_learner}} {r['metric']:<16} {f(r['median_ms'], 10)} "
            f"{f(r['iqr_ms'], 8)} {f(r['p99_ms'], 9)} {f(r['max_ms'], 9)} {r['count']:>6}  "
            f"{targets.get((r['env'], r['learner'], r['metric']), '')}".rstrip()
        )
    env_side = [
        f"{s.env} / {s.learner} {np.median(s.samples[ENV_SIDE_AGE]):.1f}"
        for s in series
        if s.samples.get(ENV_SIDE_AGE) and s.samples[ENV_SIDE_AGE] != s.samples.get("observation_age")
    ]
    if env_side:
        text = "observation age when step returned, in the env (median ms): " + ", ".join(env_side)
        lines += textwrap.wrap(text, width=max(len(head), 80), subsequent_indent="  ")
    overruns = [f"{s.env} / {s.learner}: {s.step_overruns}" for s in series if s.step_overruns]
    if overruns:
        lines.append(
            "steps that missed their deadline (the action came too late for its cycle, after the agent's compute or,"
            " in a vector env, a member's reset): " + ", ".join(overruns)
        )
    lines.append(LEGEND)
    return "\n".join(lines)


class ScriptedReachAgent:
    """A timing-only agent for the reach envs: each action is the (normalised, absolute) joint target of a random
    reachable point, picked after thinking for a uniform random 0 to ``think_ms``.

    It holds its own kinematics, so it drives an env in this process or in a worker alike; ``action_size`` pads
    the action with zeros (for envs padded by ``make_vec``).
    """

    def __init__(self, arm: str, *, think_ms: float, seed: int = 0, action_size: int | None = None) -> None:
        from uniros_async.envs.safety import SafetyChecker
        from uniros_async.kinematics import Kinematics
        from uniros_async.robots import get_robot_spec

        spec = get_robot_spec(arm)
        self.kin = Kinematics.from_spec(spec, seed=seed)
        self.safety = SafetyChecker(spec, self.kin, None)
        self.think_ms = think_ms
        self.rng = np.random.default_rng(seed)
        self._lower = np.asarray(spec.joint_lower_rad, dtype=np.float64)
        self._upper = np.asarray(spec.joint_upper_rad, dtype=np.float64)
        self.action_size = action_size or spec.n_arm_joints
        self._lo, self._hi = (0.15, -0.40, 0.05), (0.40, 0.40, 0.40)  # the reach task's goal box

    def _target(self) -> np.ndarray:
        for _ in range(200):
            q, ok = self.kin.ik(self.rng.uniform(self._lo, self._hi), rng=self.rng)
            if ok and self.safety.check(q) is None:
                return np.asarray(q, dtype=np.float64)
        raise RuntimeError("no reachable point found in 200 draws")  # pragma: no cover - the box is reachable

    def act(self) -> np.ndarray:
        """Think (sleep up to ``think_ms``, IK included) and return the next action."""
        t_end = time.monotonic() + self.rng.uniform(0.0, self.think_ms / 1e3)
        q = self._target()
        a = np.zeros(self.action_size, dtype=np.float32)
        n = len(q)
        a[:n] = (2.0 * (q - self._lower) / (self._upper - self._lower) - 1.0).clip(-1.0, 1.0)
        time.sleep(max(0.0, t_end - time.monotonic()))
        return a
