"""Timing of real-time env loops as the paper's Figures 8 to 10 show it; shared by ``uniros bench envloop`` and
``uniros bench latency``.

The metrics themselves (``loop_metrics``, ``since``) are computed in ``uniros_async.stats``; this module turns
them into records, a table with goals and a legend.

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

from uniros_async.stats import ENV_SIDE_AGE, METRICS, loop_metrics, since, summary

__all__ = ["METRICS", "ScriptedReachAgent", "Series", "format_table", "loop_metrics", "since", "to_records"]

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
