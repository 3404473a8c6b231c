"""``uniros bench simclock``: how much faster than real time the accelerated sim runs.

In one run: (1) MuJoCo alone stepping the rx200 model (the ceiling: no bus, no clock); (2) the servo sim node
on an unbounded SimClock with an env-side 10 Hz timer in the same process, the arm holding still and then
receiving a new random target every tick; (3) a whole reach episode (100 steps of 0.8 s) through the gymnasium
env with ``clock="sim"``. Each reports sim seconds per wall second.
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from uniros_async.bench.common import report

__all__ = ["SimClockBenchConfig", "main"]


@dataclasses.dataclass(frozen=True, kw_only=True)
class SimClockBenchConfig:
    sim_seconds: float = 60.0
    episodes: int = 3
    json_path: str | None = None


def _mujoco_alone(sim_s: float) -> float:
    import mujoco

    from uniros_async.robots import get_robot_spec

    m = mujoco.MjModel.from_xml_path(str(get_robot_spec("rx200").mjcf_path))
    d = mujoco.MjData(m)
    n = int(sim_s / m.opt.timestep)
    t0 = time.perf_counter()
    for _ in range(n // 50):
        mujoco.mj_step(m, d, 50)
    return sim_s / (time.perf_counter() - t0)


async def _servo_with_env_timer(sim_s: float, moving: bool) -> float:
    from uniros_async.bus import open_domain, open_node
    from uniros_async.bus.messages import Header, JointCommand, JointState
    from uniros_async.robots import get_robot_spec
    from uniros_async.sim.node import open_servo_sim
    from uniros_async.sim_clock import SimClock

    spec = get_robot_spec("rx200")
    clock = SimClock(time_scale=None)
    rng = np.random.default_rng(0)
    lo, hi = np.asarray(spec.joint_lower_rad) * 0.5, np.asarray(spec.joint_upper_rad) * 0.5
    async with open_domain("memory://") as domain, open_servo_sim(spec, domain=domain, clock=clock):
        async with open_node("env", domain=domain, namespace="/rx200", clock=clock) as env:
            js = await env.create_subscription(JointState, "joint_states")
            cmd = await env.create_publisher(JointCommand, "command")

            def tick() -> None:
                js.latest()
                if moving:
                    cmd.publish(JointCommand(header=Header(stamp_ns=clock.now_ns()), position=rng.uniform(lo, hi)))

            env.create_timer(0.1, tick)
            start_sim, t0 = clock.now_ns(), time.perf_counter()
            await clock.sleep(sim_s)
            return (clock.now_ns() - start_sim) / 1e9 / (time.perf_counter() - t0)


def _episodes(n: int) -> list[float]:
    import gymnasium as gym

    import uniros_async  # noqa: F401

    env = gym.make("uniros/Rx200Reach-v0", clock="sim", action_mode="absolute", max_episode_steps=10**9)
    out = []
    try:
        env.reset(seed=0)
        for _ in range(n):
            t0 = time.perf_counter()
            for _ in range(100):
                env.step(env.action_space.sample())
            out.append(time.perf_counter() - t0)
    finally:
        env.close()
    return out


def main(config: SimClockBenchConfig, *, log: Callable[[str], None] = print) -> list[dict[str, Any]]:
    records: list[dict[str, Any]] = []
    x = _mujoco_alone(config.sim_seconds)
    records.append({"case": "mujoco alone (ceiling)", "x_real_time": round(x, 1)})
    for moving in (False, True):
        x = asyncio.run(_servo_with_env_timer(config.sim_seconds, moving))
        label = "servo sim + 10 Hz env timer, " + ("new target every tick" if moving else "arm holding")
        records.append({"case": label, "x_real_time": round(x, 1)})
    walls = _episodes(config.episodes)
    med = float(np.median(walls))
    records.append(
        {
            "case": "reach episode, 100 steps x 0.8 s (median wall s)",
            "wall_s": round(med, 3),
            "x_real_time": round(80.0 / med, 1),
        }
    )
    lines = [f"{'case':<58} {'x real time':>11}"]
    for r in records:
        extra = f"   ({r['wall_s']} s per episode)" if "wall_s" in r else ""
        lines.append(f"{r['case']:<58} {r['x_real_time']:>11.1f}{extra}")
    report("\n".join(lines), records, config.json_path, log)
    return records
