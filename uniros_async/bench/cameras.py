"""``uniros bench cameras``: the main job's four real-time envs with and without a 30 Hz camera each.

The envs are those of ``uniros bench latency``'s ``concurrent`` scenario (rx200 sim, rx200 emulated real, ned2 sim,
ned2 emulated real), each in its own worker process (``make_vec``, one per env), wall clock, driven by the scripted
reach agent (``looptiming.ScriptedReachAgent``, absolute joint targets, a random 0 to ``think_ms`` of thinking
before each step). One row per camera setting:

- ``none``: ``obs_mode="state"``, no camera;
- ``WxH`` (``--sizes``): ``obs_mode="pixels+state"``: every env renders its arm's scene camera at 30 Hz and W x H pixels
  (camera/sim.py: EGL on Mesa's software device, in the camera's own thread of the worker process) and observes its
  newest frame.

Per env and row it prints the actuator cycle (median, IQR, p99, max: the loop's goal is the median within
``MEDIAN_GOAL_MS`` of the period and the IQR below ``IQR_GOAL_MS``), the frames rendered and skipped and the median
render time, and the frame age in the observation. The cameras a machine carries are the rows whose goals hold.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from uniros_async.bench.common import report
from uniros_async.errors import ConfigError
from uniros_async.stats import loop_metrics, since, summary

__all__ = ["CameraBenchConfig", "main", "meets_goal", "parse_sizes"]

logger = logging.getLogger(__name__)

ENVS: tuple[tuple[str, str, str], ...] = (
    ("uniros/Rx200Reach-v0", "rx200", "sim"),
    ("uniros/Rx200Reach-v0", "rx200", "emulated-real"),
    ("uniros/Ned2Reach-v0", "ned2", "sim"),
    ("uniros/Ned2Reach-v0", "ned2", "emulated-real"),
)
MEDIAN_GOAL_MS = 0.1
IQR_GOAL_MS = 0.5
CAMERA_RATE_HZ = 30.0


@dataclasses.dataclass(frozen=True, kw_only=True)
class CameraBenchConfig:
    """What ``uniros bench cameras`` runs: ``duration_s`` of wall time per row, one row per ``sizes`` entry
    (``(0, 0)``: no camera; else (width, height) of every env's 30 Hz camera)."""

    duration_s: float = 60.0
    sizes: tuple[tuple[int, int], ...] = ((0, 0), (84, 84))
    action_cycle_s: float = 0.8
    think_ms: float = 50.0
    seed: int = 0
    json_path: str | None = None

    def __post_init__(self) -> None:
        if self.duration_s <= 0:
            raise ConfigError(f"duration_s: expected > 0, got {self.duration_s}")
        for w, h in self.sizes:
            if (w, h) != (0, 0) and not (8 <= w <= 1024 and 8 <= h <= 1024):
                raise ConfigError(f"camera size: expected 8..1024 pixels each way (or 0x0: none), got {w}x{h}")


def meets_goal(median_ms: float, iqr_ms: float, period_ms: float) -> bool:
    """The loop's goal: the actuator cycle's median within ``MEDIAN_GOAL_MS`` of the period, its IQR below
    ``IQR_GOAL_MS``."""
    return abs(median_ms - period_ms) <= MEDIAN_GOAL_MS and iqr_ms < IQR_GOAL_MS


def parse_sizes(sizes: Sequence[str]) -> tuple[tuple[int, int], ...]:
    """``["none", "84x84"]`` -> ``((0, 0), (84, 84))``.

    Raises:
        ConfigError: an entry that is neither ``none`` nor ``WxH``.
    """
    out = []
    for text in sizes:
        if text == "none":
            out.append((0, 0))
            continue
        w, _, h = text.partition("x")
        if not (w.isdigit() and h.isdigit()):
            raise ConfigError(f"camera size: expected WxH (e.g. 84x84) or none, got {text!r}")
        out.append((int(w), int(h)))
    return tuple(out)


def _row(cfg: CameraBenchConfig, size: tuple[int, int]) -> list[dict[str, Any]]:
    from uniros_async.bench.looptiming import ScriptedReachAgent
    from uniros_async.runtime import make_vec

    w, h = size
    pixels = size != (0, 0)
    extra: dict[str, Any] = (
        {"obs_mode": "pixels+state", "image_size": (h, w), "camera_rate_hz": CAMERA_RATE_HZ} if pixels else {}
    )
    vecs = []
    try:
        for env_id, _, robot in ENVS:
            vecs.append(
                make_vec(
                    [(env_id, {"robot": robot})],
                    action_cycle_s=cfg.action_cycle_s,
                    action_mode="absolute",
                    max_episode_steps=10**9,
                    call_timeout_s=60.0,
                    **extra,
                )
            )
        agents = [
            ScriptedReachAgent(arm, think_ms=cfg.think_ms, seed=cfg.seed + i) for i, (_, arm, _) in enumerate(ENVS)
        ]
        for i, v in enumerate(vecs):
            v.reset(seed=cfg.seed + i)
        before = [v.call("timing_snapshot")[0] for v in vecs]
        ages: list[list[float]] = [[] for _ in ENVS]
        end = time.monotonic() + cfg.duration_s
        while time.monotonic() < end:
            for v, agent in zip(vecs, agents, strict=True):
                v.step_async(agent.act()[None, :])
            for k, v in enumerate(vecs):
                _, _, _, _, info = v.step_wait()
                if pixels:
                    ages[k].append(float(np.asarray(info["frame_age_s"])[0]) * 1e3)
        snaps = [since(v.call("timing_snapshot")[0], b) for v, b in zip(vecs, before, strict=True)]
        cams = [v.call("camera_stats")[0] if pixels else None for v in vecs]
        rates = [float(v.get_attr("env_loop_rate_hz")[0]) for v in vecs]
    finally:
        for v in vecs:
            v.close()
    out = []
    label = f"{w}x{h}" if pixels else "none"
    for (_, arm, robot), snap, rate, cam, age in zip(ENVS, snaps, rates, cams, ages, strict=True):
        act = summary(loop_metrics(snap)["actuator_cycle"])
        period_ms = 1e3 / rate
        rec: dict[str, Any] = {
            "scenario": "cameras",
            "camera": label,
            "env": f"{arm} {robot}",
            "period_ms": period_ms,
            "actuator_median_ms": act["p50"],
            "actuator_iqr_ms": act["iqr"],
            "actuator_p99_ms": act["p99"],
            "actuator_max_ms": act["max"],
            "ticks": act["count"],
            "goal_met": meets_goal(act["p50"], act["iqr"], period_ms),
        }
        if cam is not None:
            rec.update(frames=cam["frames"], skipped=cam["skipped"], render_median_ms=cam["render_median_ms"])
            rec["frame_age_median_ms"] = float(np.median(age)) if age else float("nan")
        out.append(rec)
    return out


def format_table(records: Sequence[dict[str, Any]], cfg: CameraBenchConfig) -> str:
    """The table: one line per camera setting and env."""
    head = (
        f"{'camera':<9} {'env':<20} {'act. med':>9} {'act. IQR':>9} {'act. p99':>9} {'act. max':>9}  "
        f"{'frames':>7} {'skipped':>7} {'render':>7} {'age':>6}  goal"
    )
    lines = [
        f"actuator cycle (ms) of the four real-time envs, each with a {CAMERA_RATE_HZ:g} Hz camera of the size given "
        f"(none: no camera); {cfg.duration_s:g} s per row",
        head,
        "-" * len(head),
    ]
    for r in records:
        cam = (
            f"{r['frames']:>7} {r['skipped']:>7} {r['render_median_ms']:>7.2f} {r['frame_age_median_ms']:>6.1f}"
            if "frames" in r
            else f"{'':>7} {'':>7} {'':>7} {'':>6}"
        )
        lines.append(
            f"{r['camera']:<9} {r['env']:<20} {r['actuator_median_ms']:>9.2f} {r['actuator_iqr_ms']:>9.3f} "
            f"{r['actuator_p99_ms']:>9.2f} {r['actuator_max_ms']:>9.2f}  {cam}  {'met' if r['goal_met'] else 'MISSED'}"
        )
    lines.append(
        f"goal: actuator cycle median within {MEDIAN_GOAL_MS} ms of the period (100 ms rx200, 40 ms ned2) and IQR "
        f"below {IQR_GOAL_MS} ms. frames/skipped: rendered and published, and camera ticks skipped while the renderer "
        "was busy; render: median ms per frame; age: median frame age in the observation at each step (ms)"
    )
    return "\n".join(lines)


def main(config: CameraBenchConfig, *, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Run every row, print the table, write JSON when asked; returns the records."""
    records: list[dict[str, Any]] = []
    for size in config.sizes:
        records += _row(config, size)
    report(format_table(records, config), records, config.json_path, log)
    return records
